"""Reading and validating a batch manifest (``runner batch shots.yaml``): every error found,
each with file, line and column, before anything runs.

Schema
------
.. code-block:: yaml

    defaults:                        # optional: fields every job takes unless it sets its own
      pipeline: ../../pipeline.yaml  # paths are relative to the manifest's folder
      target: ../packs/target        # binds the pipeline input `target` (--input target=PATH)
      set: [synthesize.mode=full]    # --set overrides; a job's own come after (they win)
    jobs:                            # one entry per shot, keyed by a unique name
      calm:
        clip: ../clips/calm.mp4      # the pipeline's clip input (--in: a video, or a folder of photos)
        out: out/calm                # --out; default out/<name> next to the manifest
      live:
        clip: ../clips/live.mp4
        inputs: {target: ../packs/target}   # any pipeline input (--input NAME=PATH)
        set: [compensate.neutral_frame=3]

Each job is checked as ``runner run`` would check its command line (the pipeline loaded with
its overrides, every input bound and present), its ``out`` folder is checked for a user's
folder at a stage's name, and no two jobs may publish to the same folder. The YAML is read with
:mod:`runner.safe_yaml` (no aliases, no unknown tags).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from runner.config import NAME_RE, ConfigError, Pipeline, _Reader, bind_inputs, clip_inputs, load_pipeline, read_yaml_file
from runner.publish import conflicts
from runner.registry import Registry

TOP_KEYS = ("defaults", "jobs")
JOB_KEYS = ("pipeline", "clip", "target", "inputs", "set", "out")
DEFAULT_KEYS = ("pipeline", "target", "inputs", "set")
PATH_KEYS = ("pipeline", "clip", "target", "out")


@dataclass(frozen=True)
class Job:
    """One validated shot of a batch: what ``runner run PIPELINE --in CLIP --input NAME=PATH ...
    --set ... --out OUT`` would be given. Paths are absolute (a cluster's hosts must see them at
    the same place). Plain strings only, so that a job travels to a Ray worker as it is."""

    name: str
    pipeline: str
    clip: str | None
    named: tuple[str, ...] = ()  # "NAME=PATH", as --input
    overrides: tuple[str, ...] = ()  # "stage.param=value", as --set
    out: str = ""


@dataclass
class _Fields:
    """A job's (or the defaults') fields: value and node of each."""

    values: dict[str, Any] = field(default_factory=dict)
    nodes: dict[str, yaml.Node] = field(default_factory=dict)


def load_manifest(path: Path, registry: Registry) -> list[Job]:
    """Read and validate a batch manifest.

    Parameters
    ----------
    path
        The manifest (``shots.yaml``); relative paths in it are relative to its folder.
    registry
        Where the pipelines' stage names are looked up.

    Returns
    -------
    list of Job
        In the manifest's order.

    Raises
    ------
    ConfigError
        With every problem found, positioned in the manifest (or in a job's pipeline file when
        the problem is there).
    """
    path = Path(path)
    root = read_yaml_file(path, empty=("jobs", "empty manifest"))
    r = _Reader()
    top = {name: vnode for name, _, vnode in r.mapping(root, "", TOP_KEYS)}
    base = path.resolve().parent
    defaults = _read_fields(r, top["defaults"], "defaults", DEFAULT_KEYS, base) if "defaults" in top else _Fields()
    entries = r.mapping(top["jobs"], "jobs", None) if "jobs" in top else []
    if not entries and not r.issues:
        r.error(top.get("jobs", root), "jobs", "missing: a manifest needs a `jobs` mapping with at least one job")
    jobs: list[Job] = []
    outs: dict[Path, str] = {}
    pipelines: dict[tuple[str, tuple[str, ...]], Pipeline | ConfigError] = {}
    for name, knode, vnode in entries:
        key = f"jobs.{name}"
        if not NAME_RE.match(name):
            r.error(knode, key, "invalid name (letters, digits, '_' and '-'; no dots)")
            continue
        own = _read_fields(r, vnode, key, JOB_KEYS, base)
        job = _job(r, name, knode, vnode, own, defaults, base, registry, pipelines)
        if job is None:
            continue
        out = Path(job.out)
        node = own.nodes.get("out", knode)
        if out in outs:
            r.error(node, f"{key}.out", f"same output folder as job {outs[out]!r}: {out}")
            continue
        outs[out] = name
        jobs.append(job)
    if r.issues:
        raise ConfigError(r.issues)
    return jobs


def _read_fields(r: _Reader, node: yaml.Node, key: str, allowed: tuple[str, ...], base: Path) -> _Fields:
    """Type-checked fields of a job or of ``defaults``; paths made absolute against ``base``."""
    fields = _Fields()
    for name, _, vnode in r.mapping(node, key, allowed):
        fkey = f"{key}.{name}"
        value = r.value(vnode)
        if name in PATH_KEYS:
            if not isinstance(value, str) or not value:
                r.error(vnode, fkey, f"wrong type: expected a path string, got {value!r}")
                continue
            value = os.path.normpath(base / value)
        elif name == "inputs":
            if not isinstance(value, dict) or not all(isinstance(k, str) and isinstance(v, str) and v for k, v in value.items()):
                r.error(vnode, fkey, f"wrong type: expected a mapping of input name to path, got {value!r}")
                continue
            value = {k: os.path.normpath(base / v) for k, v in value.items()}
        elif name == "set":
            if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
                r.error(vnode, fkey, f"wrong type: expected a list of 'stage.param=value' strings, got {value!r}")
                continue
        fields.values[name], fields.nodes[name] = value, vnode
    return fields


def _job(
    r: _Reader,
    name: str,
    knode: yaml.Node,
    vnode: yaml.Node,
    own: _Fields,
    defaults: _Fields,
    base: Path,
    registry: Registry,
    pipelines: dict[tuple[str, tuple[str, ...]], Pipeline | ConfigError],
) -> Job | None:
    """The job ``name`` checked as ``runner run`` checks its command line; None (issues
    recorded) if it is invalid."""
    key = f"jobs.{name}"
    count = len(r.issues)

    def field_of(fname: str) -> tuple[Any, yaml.Node] | None:
        for fields in (own, defaults):
            if fname in fields.values:
                return fields.values[fname], fields.nodes[fname]
        return None

    pipeline = field_of("pipeline")
    if pipeline is None:
        r.error(vnode, f"{key}.pipeline", "missing: the pipeline this job runs (here or in `defaults`)")
        return None
    named: dict[str, tuple[str, yaml.Node]] = {}
    for fields in (defaults, own):  # the job's own inputs win
        named.update({k: (v, fields.nodes["inputs"]) for k, v in fields.values.get("inputs", {}).items()})
        if "target" in fields.values:
            named["target"] = (fields.values["target"], fields.nodes["target"])
    overrides = [
        (text, fields.nodes["set"].value[i])  # each string's own node
        for fields in (defaults, own)
        for i, text in enumerate(fields.values.get("set", []))
    ]
    clip = field_of("clip")

    loaded_key = (pipeline[0], tuple(text for text, _ in overrides))
    if loaded_key not in pipelines:
        try:
            pipelines[loaded_key] = load_pipeline(Path(pipeline[0]), registry, overrides=list(loaded_key[1]))
        except ConfigError as exc:
            pipelines[loaded_key] = exc
    loaded = pipelines[loaded_key]
    if isinstance(loaded, ConfigError):
        for issue in loaded.issues:
            if issue.where.file == "--set":  # an override: positioned at the manifest's `set`
                node = next((n for text, n in overrides if issue.key in (text, text.partition("=")[0])), vnode)
                r.error(node, f"{key}.set", f"{issue.key}: {issue.message}")
            elif issue.where.file == str(pipeline[0]) and not issue.where.line:
                r.error(pipeline[1], f"{key}.pipeline", issue.message)
            elif issue not in r.issues:  # positioned in the pipeline file itself, said once
                r.issues.append(issue)
        return None

    _check_inputs(r, key, loaded, clip, named)
    if len(r.issues) > count:
        return None
    try:
        bind_inputs(loaded, clip=None if clip is None else Path(clip[0]), named=[f"{k}={v}" for k, (v, _) in named.items()])
    except ConfigError as exc:  # an input left without a value, or one a stage refuses (a bad pack)
        for issue in exc.issues:
            message = issue.message
            if message.startswith("missing input: no value given"):
                message = f"{message.split(' (use ')[0]} (give it in the job or in `defaults`)"
            r.error(knode, f"{key}: {issue.key}", message)
        return None

    out = Path(own.values["out"] if "out" in own.values else base / "out" / name)
    publishing = [n for n, node in loaded.stages.items() if "files" in node.cls.outputs.values()]
    for folder, why in conflicts(out, publishing):
        r.error(own.nodes.get("out", knode), f"{key}.out", f"{folder}: {why}")
    if len(r.issues) > count:
        return None
    return Job(
        name=name,
        pipeline=pipeline[0],
        clip=None if clip is None else clip[0],
        named=tuple(f"{k}={v}" for k, (v, _) in named.items()),
        overrides=loaded_key[1],
        out=str(out),
    )


def _check_inputs(
    r: _Reader, key: str, loaded: Pipeline, clip: tuple[str, yaml.Node] | None, named: dict[str, tuple[str, yaml.Node]]
) -> None:
    """Record an issue, at its manifest node, for each input of job ``key`` that the pipeline
    does not declare or that does not exist (a file, or a folder for a ``dir`` input)."""
    clips = clip_inputs(loaded)
    given = [("clip", name, clip) for name in clips[:1] if clip is not None]
    if clip is not None and len(clips) != 1:
        r.error(clip[1], f"{key}.clip", f"{loaded.path} has {len(clips)} clip inputs; bind one with `inputs`")
    for name, value in named.items():
        field_name = "target" if name == "target" else "inputs"
        if name not in loaded.inputs:
            r.error(
                value[1],
                f"{key}.{field_name}",
                f"unknown pipeline input {name!r} of {loaded.path} (declared: {', '.join(loaded.inputs) or 'none'})",
            )
        else:
            given.append((field_name, name, value))
    for field_name, name, (path, node) in given:
        is_dir = loaded.inputs[name].type == "dir"
        if not (Path(path).is_dir() if is_dir else Path(path).is_file()):
            r.error(node, f"{key}.{field_name}", f"{path}: no such {'folder' if is_dir else 'file'}")
