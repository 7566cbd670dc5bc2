"""The local Ray of ``runner batch``: only the processes a batch on one machine uses.

``ray.init()`` starting a local Ray also starts three Python processes that a fixed-size,
one-machine batch never uses: the autoscaler monitor (nothing to scale), the log monitor (the
workers' output is kept out of the driver) and the dashboard head (with the dashboard off it
loads only its usage-statistics module, yet ``ray.init`` waits until it has published its URL
before it starts the raylet). On 2 cores each of them delays the others' start, and at
shut-down Ray waits its fixed 1 s grace for the monitor to end. :func:`start_local_ray` starts
the head node the way ``ray.init`` does (the same ``ray._private.node.Node``, token
authentication as for a local ``ray.init``, a reaper that ends the processes if this one dies)
without those three, with the raylet prestarting its worker processes as it starts
(``enable_worker_prestart``) rather than when the driver connects (the driver's connection
then waited for them) and its workers at the driver's priority (``worker_niceness`` 0, where Ray
nices them by 15), then connects this process with the public ``ray.init(address=...)``.
The node API is Ray's private one (Ray is pinned, and a test pins this behaviour); where it is
missing the batch falls back to ``ray.init()`` with a note. ``docs/batch.md`` gives the
measured seconds.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import ray

RAY_OPTIONS = {"log_to_driver": False, "logging_level": logging.ERROR}  # every ray.init of a batch driver
# The raylet's settings: workers prestarted as the node registers (not when the driver connects),
# and at the driver's priority (Ray's default nice 15 gave a job a few per cent of a core beside
# other processes: a job computes as `runner run` does).
SYSTEM_CONFIG = {"enable_worker_prestart": True, "worker_niceness": 0}


def start_local_ray(cpus: int, *, note: Callable[[str], None]) -> Callable[[], None]:
    """Start a local Ray of ``cpus`` CPUs, connect this process as its driver; returns the
    function that disconnects and stops it (every process it started).

    Parameters
    ----------
    cpus
        The node's logical CPUs (Ray prestarts one worker process per CPU).
    note
        Receives one line if Ray's node API is missing and ``ray.init()`` starts the Ray instead
        (the whole local Ray: slower start-up and shut-down).

    Raises
    ------
    ValueError
        ``cpus`` is not a positive int.
    """
    if isinstance(cpus, bool) or not isinstance(cpus, int) or cpus < 1:
        raise ValueError(f"cpus must be a positive int, got {cpus!r}")
    try:
        from ray._private.authentication.authentication_token_setup import (
            enable_token_auth_by_default,
            ensure_token_if_auth_enabled,
        )
        from ray._private.node import Node
        from ray._private.parameter import RayParams
    except ImportError as exc:
        note(f"note: Ray's node API is missing ({exc}); starting the whole local Ray with ray.init()")
        ray.init(address="local", num_cpus=cpus, include_dashboard=False, **RAY_OPTIONS)
        return ray.shutdown  # type: ignore[no-any-return]  # Ray is read as untyped

    class BatchNode(Node):  # type: ignore[misc]  # Ray is read as untyped
        """A head node without the dashboard head (the API server)."""

        def start_api_server(self, *, include_dashboard: bool | None, raise_on_failure: bool) -> None:
            """Start nothing: no dashboard, no job or state API on a batch's own Ray."""

    enable_token_auth_by_default()  # as ray.init() does for a local Ray: RAY_AUTH_MODE=token unless set
    ensure_token_if_auth_enabled({}, create_token_if_missing=True)
    params = RayParams(
        num_cpus=cpus, include_dashboard=False, no_monitor=True, include_log_monitor=False, _system_config=SYSTEM_CONFIG
    )
    node = BatchNode(ray_params=params, head=True, shutdown_at_exit=False, spawn_reaper=True, ray_init_cluster=True)
    try:
        ray.init(address=node.gcs_address, **RAY_OPTIONS)
    except BaseException:
        node.kill_all_processes(check_alive=False, allow_graceful=True)
        raise

    def stop() -> None:
        ray.shutdown()  # the driver's connection; then the node, as ray.shutdown() ends the Ray it started
        node.destroy_external_storage()
        node.kill_all_processes(check_alive=False, allow_graceful=True)

    return stop
