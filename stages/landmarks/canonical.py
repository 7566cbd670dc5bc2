"""MediaPipe's canonical 3D face mesh, read from the Face Landmarker model bundle.

The Face Landmarker bundle (``models/face_landmarker.task``, a zip) carries
``geometry_pipeline_metadata_landmarks.binarypb``, a ``GeometryPipelineMetadata`` protocol
buffer (``mediapipe/modules/face_geometry/protos/geometry_pipeline_metadata.proto``) whose field 1
is the canonical face mesh (``Mesh3d``): field 3 the vertex buffer, five floats per vertex
``(x, y, z, u, v)`` — position in centimetres in MediaPipe's face frame (x to the face's left as
seen by the camera, i.e. image right; y up; z towards the camera) and texture coordinates —,
field 4 the triangle index buffer. This is the mean face the landmarker's facial transformation
matrix maps into camera space; the project uses it as the generic 3D face model (paper Sec. 12.1)
when no performer pack gives one.

The message is decoded here from the protocol-buffer wire format directly (varint, 32-bit and
length-delimited fields, packed or not), so no generated protobuf classes are needed.
"""

from __future__ import annotations

import functools
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MODEL_PATH = Path(__file__).parent / "models" / "face_landmarker.task"
METADATA = "geometry_pipeline_metadata_landmarks.binarypb"


@dataclass(frozen=True)
class CanonicalMesh:
    """The canonical face mesh.

    Attributes
    ----------
    vertices : (V, 3) float64
        Positions in cm, MediaPipe's face frame (x image-right, y up, z towards the camera);
        V = 468 (the mesh without the iris points 468-477 of the landmarker's output).
    uv : (V, 2) float64
        Texture coordinates in [0, 1].
    triangles : (F, 3) int64
        Vertex indices of each triangle.
    """

    vertices: np.ndarray
    uv: np.ndarray
    triangles: np.ndarray


def _varint(data: bytes, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = data[i]
        i += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if byte < 0x80:
            return value, i


def _fields(data: bytes):
    """Yield ``(field number, wire type, value)``: an int for varints, bytes otherwise."""
    i = 0
    while i < len(data):
        tag, i = _varint(data, i)
        number, wire = tag >> 3, tag & 7
        if wire == 0:
            value, i = _varint(data, i)
        elif wire == 1:
            value, i = data[i : i + 8], i + 8
        elif wire == 2:
            size, i = _varint(data, i)
            value, i = data[i : i + size], i + size
        elif wire == 5:
            value, i = data[i : i + 4], i + 4
        else:
            raise ValueError(f"unsupported protobuf wire type {wire} for field {number}")
        yield number, wire, value


def _floats(items: list[tuple[int, bytes]]) -> list[float]:
    out: list[float] = []
    for wire, value in items:
        out.extend(struct.unpack(f"<{len(value) // 4}f", value))  # packed (2) or single (5)
    return out


def _uints(items: list[tuple[int, bytes | int]]) -> list[int]:
    out: list[int] = []
    for wire, value in items:
        if wire == 0:
            out.append(value)
            continue
        i = 0
        while i < len(value):
            v, i = _varint(value, i)
            out.append(v)
    return out


def parse_mesh3d(data: bytes) -> CanonicalMesh:
    """Decode a serialized ``Mesh3d`` (vertex type ``VERTEX_PT``, triangles)."""
    buffers: dict[int, list] = {3: [], 4: []}
    for number, wire, value in _fields(data):
        if number in buffers:
            buffers[number].append((wire, value))
    vertex = np.asarray(_floats(buffers[3]), dtype=np.float64)
    index = np.asarray(_uints(buffers[4]), dtype=np.int64)
    if vertex.size == 0 or vertex.size % 5 or index.size % 3:
        raise ValueError(
            f"Mesh3d: expected 5 floats per vertex and 3 indices per triangle, got {vertex.size} floats and {index.size} indices"
        )
    vertex = vertex.reshape(-1, 5)
    triangles = index.reshape(-1, 3)
    if triangles.max() >= len(vertex):
        raise ValueError(f"Mesh3d: a triangle names vertex {triangles.max()} of {len(vertex)}")
    return CanonicalMesh(vertices=vertex[:, :3], uv=vertex[:, 3:], triangles=triangles)


@functools.cache
def canonical_mesh(model_path: Path = MODEL_PATH) -> CanonicalMesh:
    """The canonical face mesh stored in the Face Landmarker bundle at ``model_path``.

    Raises
    ------
    ValueError
        The bundle has no geometry metadata, or the mesh in it cannot be decoded.
    """
    try:
        with zipfile.ZipFile(model_path) as bundle:
            data = bundle.read(METADATA)
    except (OSError, KeyError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{model_path}: cannot read {METADATA} from the model bundle: {exc}") from exc
    for number, wire, value in _fields(data):
        if number == 1 and wire == 2:
            return parse_mesh3d(value)
    raise ValueError(f"{model_path}: {METADATA} holds no canonical mesh (field 1)")
