"""Test helpers for `tacsplat view`: start it in a subprocess, and read the scene it serves the way a browser
does (viser's websocket protocol, messages named by viser's own message classes)."""

from __future__ import annotations

import base64
import contextlib
import os
import re
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass

import msgspec
import numpy as np
import zstandard

URL_LINE = re.compile(r"tacsplat view: \w+ .* at (http://[\w.\-]+:(\d+)) \(Ctrl-C to stop\)")


@contextlib.contextmanager
def served(path, *options, timeout: float = 180.0):
    """Run ``tacsplat view PATH --port 0`` with no display until the block ends (Ctrl-C); yields its URL. It starts
    with SIGINT ignored, as a script's background job does (Python then leaves Ctrl-C ignored): Ctrl-C must stop
    it all the same."""
    headless = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    # -X faulthandler: a process that does not stop on Ctrl-C is sent SIGABRT, which prints where each thread is
    process = subprocess.Popen(
        [sys.executable, "-X", "faulthandler", "-m", "tacsplat", "view", str(path), "--port", "0", *options],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=headless,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    output: list[str] = []
    found = threading.Event()

    def read() -> None:
        for line in process.stdout:
            output.append(line)
            if URL_LINE.search(line):
                found.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        if not found.wait(timeout):
            raise AssertionError(f"no URL printed in {timeout} s:\n{''.join(output)}")
        yield next(URL_LINE.search(line).group(1) for line in output if URL_LINE.search(line))
    finally:
        process.send_signal(signal.SIGINT)
        try:
            code = process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.send_signal(signal.SIGABRT)
            reader.join(timeout=30)
            process.kill()
            raise AssertionError(f"tacsplat view did not stop within 30 s of Ctrl-C:\n{''.join(output)}") from None
        assert code == 0, f"tacsplat view exited {code}:\n{''.join(output)}"


@dataclass
class Node:
    """A scene node as a client receives it: viser's message class, its props and binary buffers."""

    name: str
    message: type
    props: dict
    buffers: dict[str, np.ndarray]
    visible: bool = True


def _read_buffers(value, buffers: list[np.ndarray]):
    """``value`` with viser's binary placeholders ({"__binary_index": i, "dtype": ...}) replaced by arrays."""
    if isinstance(value, dict):
        if "__binary_index" in value and "dtype" in value:
            return buffers[value["__binary_index"]].view(np.dtype(value["dtype"]))
        return {k: _read_buffers(v, buffers) for k, v in value.items()}
    if isinstance(value, list):
        return [_read_buffers(v, buffers) for v in value]
    return value


def _aligned_buffers(data: bytes, offset: int, lengths) -> list[np.ndarray]:
    """The binary buffers after a payload: each starts at the next multiple of 8 bytes."""
    out = []
    for length in lengths:
        offset += (8 - offset % 8) % 8
        out.append(np.frombuffer(data, np.uint8, length, offset))
        offset += length
    return out


def _apply(nodes: dict[str, Node], messages: list[dict], buffers: list[np.ndarray]) -> None:
    """Apply viser messages (as decoded dicts) to ``nodes``: creations, removals, visibility changes."""
    from viser import _messages

    classes = {c.__name__: c for c in _messages.Message.get_subclasses()}
    for raw in messages:
        cls = classes[raw["type"]]
        if issubclass(cls, _messages._CreateSceneNodeMessage):
            props = _read_buffers(raw.get("props", {}), buffers)
            arrays = {k: v for k, v in props.items() if isinstance(v, np.ndarray)}
            nodes[raw["name"]] = Node(raw["name"], cls, props, arrays)
        elif cls is _messages.RemoveSceneNodeMessage:
            nodes.pop(raw["name"], None)
        elif cls is _messages.SetSceneNodeVisibilityMessage and raw["name"] in nodes:
            nodes[raw["name"]].visible = raw["visible"]


def served_scene(url: str, timeout: float = 60.0) -> dict[str, Node]:
    """The scene nodes a new browser connection receives from a viewer at ``url`` (its replay of the scene)."""
    import viser
    from viser import _messages
    from websockets.sync.client import connect

    nodes: dict[str, Node] = {}
    ws_url = url.replace("http://", "ws://")
    with connect(ws_url, subprotocols=[f"viser-v{viser.__version__}"], max_size=None, open_timeout=timeout) as ws:
        while True:
            frame = ws.recv(timeout=timeout)
            inner, compressed = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
            payload = msgspec.msgpack.decode(
                zstandard.ZstdDecompressor().decompress(frame[16 : 16 + compressed], max_output_size=inner)
            )
            buffers = _aligned_buffers(frame, 16 + compressed, payload["binaryBufferLengths"])
            _apply(nodes, payload["messages"], buffers)
            if any(m["type"] == _messages.ReplayDoneMessage.__name__ for m in payload["messages"]):
                return nodes


def exported_scene(html: str) -> dict[str, Node]:
    """The scene nodes of a page written by ``tacsplat view --export`` (viser's embedded recording)."""
    match = re.search(r'window.__VISER_EMBED_DATA__="([A-Za-z0-9+/=]+)"', html)
    assert match, "no embedded scene in the page"
    data = base64.b64decode(match.group(1))
    inner = zstandard.ZstdDecompressor().decompress(data[8:], max_output_size=int.from_bytes(data[:8], "little"))
    length = int.from_bytes(inner[:8], "little")
    payload = msgspec.msgpack.decode(inner[8 : 8 + length])
    buffers = _aligned_buffers(inner, 8 + length, payload["binaryBufferLengths"])
    nodes: dict[str, Node] = {}
    _apply(nodes, [message for _, message in payload["messages"]], buffers)
    return nodes


def splat_count(node: Node) -> int:
    """Gaussians in a splat node (viser packs each in 8 uint32 words)."""
    return node.buffers["buffer"].size // 8
