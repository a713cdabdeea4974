"""A minimal viser websocket client for the live-view tests: what a browser receives and sends.

It speaks viser's wire format (viser/infra/_infra.py, ``_message_producer``): each frame is
``[u64 msgpack size][u64 compressed size][zstd(msgpack)][padding][binary buffers, 8-aligned]``,
arrays replaced by ``{"__binary_index": i, "dtype": ...}``; client -> server messages are plain
msgpack dicts with a ``type``.
"""

from __future__ import annotations

import threading
import time

import msgspec
import numpy as np
import viser
import websockets.sync.client
import zstandard
from viser import _messages as vm


def _decode_frame(raw: bytes) -> list[dict]:
    inner_size = int.from_bytes(raw[0:8], "little")
    compressed_size = int.from_bytes(raw[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(raw[16:16 + compressed_size], max_output_size=inner_size)
    payload = msgspec.msgpack.decode(inner)
    offset = 16 + compressed_size
    buffers = []
    for length in payload["binaryBufferLengths"]:
        offset += (8 - offset % 8) % 8
        buffers.append(raw[offset:offset + length])
        offset += length

    def resolve(value):
        if isinstance(value, dict):
            if "__binary_index" in value and "dtype" in value:
                return np.frombuffer(buffers[value["__binary_index"]], dtype=np.dtype(value["dtype"]))
            return {k: resolve(v) for k, v in value.items()}
        if isinstance(value, list):
            return [resolve(v) for v in value]
        return value

    return [resolve(m) for m in payload["messages"]]


class ViewClient:
    """Connects to a viser server, records every message received (with its arrival time)."""

    def __init__(self, url: str) -> None:
        ws_url = url.replace("http://", "ws://")
        self._ws = websockets.sync.client.connect(ws_url, subprotocols=[f"viser-v{viser.__version__}"],
                                                  max_size=None)
        self.messages: list[tuple[float, dict]] = []
        self._lock = threading.Lock()
        self.closed = threading.Event()
        self._thread = threading.Thread(target=self._receive, daemon=True)
        self._thread.start()

    def _receive(self) -> None:
        try:
            while True:
                raw = self._ws.recv()
                now = time.perf_counter()
                for message in _decode_frame(raw):
                    with self._lock:
                        self.messages.append((now, message))
        except Exception:  # connection closed
            self.closed.set()

    def updates(self, name: str, prop: str) -> list[tuple[float, object]]:
        """``(arrival time, value)`` of every update of ``prop`` on scene node ``name``."""
        with self._lock:
            found = []
            for t, m in self.messages:
                if m.get("type") == "SceneNodeUpdateMessage" and m.get("name") == name and prop in m["updates"]:
                    found.append((t, m["updates"][prop]))
                elif m.get("name") == name and m.get("type", "").endswith("Message") and "props" in m \
                        and prop in m["props"]:
                    found.append((t, m["props"][prop]))
            return found

    def poses(self, name: str, kind: str) -> list[tuple[float, tuple]]:
        """Arrival time and value of every ``SetPositionMessage`` (``kind="position"``) or
        ``SetOrientationMessage`` (``kind="wxyz"``) for node ``name``."""
        message_type = "SetPositionMessage" if kind == "position" else "SetOrientationMessage"
        with self._lock:
            return [(t, tuple(m[kind])) for t, m in self.messages
                    if m.get("type") == message_type and m.get("name") == name]

    def send(self, message) -> None:
        """Sends a viser message (an instance of a ``viser._messages`` class)."""
        self._ws.send(msgspec.msgpack.encode(message.as_serializable_dict()))

    def drag(self, name: str, displacement, steps: int, pause: float) -> tuple[np.ndarray, tuple]:
        """Drags gizmo ``name`` as a mouse would: by ``displacement`` [m] from its last position,
        in ``steps`` equal moves ``pause`` [s] apart between a drag start and a drag end, its last
        orientation held.

        Returns:
            ``(target, q0)``: where the drag ended [m], and the orientation held (w, x, y, z).
        """
        p0 = np.array(self.poses(name, "position")[-1][1])
        q0 = tuple(self.poses(name, "wxyz")[-1][1])
        target = p0 + np.asarray(displacement, dtype=np.float64)
        self.send(vm.TransformControlsDragStartMessage(name=name))
        for a in np.linspace(0.0, 1.0, steps + 1)[1:]:
            self.send(vm.TransformControlsUpdateMessage(name=name, wxyz=q0,
                                                        position=tuple(map(float, p0 + a * (target - p0)))))
            time.sleep(pause)
        self.send(vm.TransformControlsDragEndMessage(name=name))
        return target, q0

    def close(self) -> None:
        self._ws.close()
        self._thread.join(timeout=5.0)
