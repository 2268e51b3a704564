"""A quad as a glTF document (positions, texture coordinates and indices in one binary buffer) and
the GLB container around a document, for the tests that build glTF input by hand."""

from __future__ import annotations

import copy
import json
import struct

import numpy as np

POSITIONS = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
UVS = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], np.float32)
INDICES = np.array([0, 1, 2, 2, 1, 3], np.uint16)
#: positions (48 bytes), texture coordinates (32) and indices (12), padded to 4 bytes
BINARY = POSITIONS.tobytes() + UVS.tobytes() + INDICES.tobytes()
#: the quad's buffer, views and accessors (0: POSITION, 1: TEXCOORD_0, 2: indices)
BUFFERS = {
    "buffers": [{"byteLength": len(BINARY)}],
    "bufferViews": [
        {"buffer": 0, "byteOffset": 0, "byteLength": 48},
        {"buffer": 0, "byteOffset": 48, "byteLength": 32},
        {"buffer": 0, "byteOffset": 80, "byteLength": 12},
    ],
    "accessors": [
        {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]},
        {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
        {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"},
    ],
}


def buffers() -> dict:
    """A copy of :data:`BUFFERS` to put in a document."""
    return copy.deepcopy(BUFFERS)


def chunk(kind: bytes, data: bytes) -> bytes:
    """A GLB chunk: its length, its type and ``data`` padded to 4 bytes (spaces for JSON)."""
    data += (b" " if kind == b"JSON" else b"\0") * (-len(data) % 4)
    return struct.pack("<I4s", len(data), kind) + data


def json_chunk(doc: dict) -> bytes:
    return chunk(b"JSON", json.dumps(doc).encode())


def glb(*chunks: bytes, length: int | None = None) -> bytes:
    """The GLB header (its stated ``length``, by default the true one) and ``chunks``."""
    body = b"".join(chunks)
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body) if length is None else length) + body


def glb_bytes(doc: dict, binary: bytes = BINARY) -> bytes:
    """A well-formed GLB of ``doc`` and its binary chunk."""
    return glb(json_chunk(doc), chunk(b"BIN\0", binary))
