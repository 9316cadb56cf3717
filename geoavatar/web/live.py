"""The live player server: the page, its bundle and an avatar over HTTP, posed meshes over a websocket (/ws), and,
for `speak --microphone`, the page's microphone back over the same websocket.

    server = LiveServer(assets, host, port, on_edit=None, on_audio=None,
                        on_microphone_error=None).start()            # LiveServerError naming --port when taken
    server.send_vertices(vertices, read_time, code, capture_time)    # [V, 3], code [6] or None; from any thread
    server.stop()

One asyncio loop in a thread serves everything on one port. send_vertices keeps the newest PENDING (2) meshes per
browser: while a browser's previous mesh is still being written (or the loop has not run yet), newer ones wait, and
one more drops the oldest waiting (counted in `dropped`), so a slow connection never builds a queue, and one late
turn of the loop (the machine busy for a moment) costs no frame. Latency: `read_time` (time.perf_counter() when the
source frame was read) to the moment the message is written to every connected browser's socket (`latency_ms`). A
text message from the page (view's sliders, JSON) is handed to `on_edit` in a worker thread; it may answer with
send_vertices.

The wire format is web/src/live.js's (all little-endian):

    server -> page, kind 1, a posed mesh:   uint32 1, uint32 sequence, float64 send time (Unix seconds),
                                            float32 vertices [V * 3], then float32 head pose code [6] when the avatar's
                                            hair follows the head's turn (web/pack.py)
    server -> page, kind 3, a mesh posed    uint32 3, uint32 sequence, float64 send time, float64 capture time (Unix
      from sound:                           seconds, the page's clock: when the mesh's own instant of sound was
                                            captured), then the vertices and code as kind 1; the page
                                            records drawn time - capture time (stats.soundToPicture)
    page -> server, kind 2, ~20 ms of the   uint32 2, uint32 sequence (0, 1, ... per page), float64 capture time (Unix
      microphone (live "speak"):            seconds by the page's clock, performance.timeOrigin + now: when the
                                            chunk's last sample was captured), int16 samples at 16 kHz mono
    page -> server, text JSON:              {"type": "edit", ...} (view's sliders) -> on_edit(dict);
                                            {"type": "microphone", "error": "NotAllowedError: ..."} (getUserMedia
                                            failed, or the microphone stopped) -> on_microphone_error(str)

on_audio(samples float32 [n] in [-1, 1) at AUDIO_RATE, capture_time float, sequence int) is called for every chunk,
in order, in a worker thread of its own (the server loop never waits for it; chunks queue while it runs). One page
at a time is the microphone: the first page that sends sound, until it disconnects; sound from other pages is
dropped (counted in `audio_ignored`); a new page starts its sequence at 0 again. An exception raised by on_audio
or on_microphone_error is printed to stderr and kept in `audio_error` (the first one), for the caller to raise.
"""

from __future__ import annotations

import asyncio
import errno
import json
import socket
import struct
import threading
import time
import traceback
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Callable
from urllib.parse import urlsplit

import numpy as np
import torch

from geoavatar.errors import GeoAvatarError
from geoavatar.web.pack import PLAYER_FILES, PlayerAssets, static_dir

KIND_VERTICES = 1  # server -> page: a posed mesh
KIND_AUDIO = 2  # page -> server: a chunk of the microphone
KIND_SOUND_VERTICES = 3  # server -> page: a posed mesh with the capture time of the sound it was posed from
AUDIO_RATE = 16000  # Hz of the page's microphone chunks
HEADER = struct.Struct("<IId")  # kind, sequence, a time in Unix seconds (kinds 1, 2; kind 3 adds a float64)
CONTENT_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                 ".json": "application/json", ".bin": "application/octet-stream", ".wav": "audio/wav"}


def check_address(host: str, port: int) -> None:
    """LiveServerError (one line, naming --host / --port) when `host`:`port` cannot be listened on: probed with a
    plain socket, so a command finds out before it poses anything (port 0: any free port, always fine)."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM,
                                                             flags=socket.AI_PASSIVE)[0]
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds
            probe.bind(address)
    except (OSError, ValueError) as err:  # ValueError (UnicodeError): a host name that cannot be encoded
        raise _address_error(host, port, err) from err


def _address_error(host: str, port: int, err: BaseException) -> "LiveServerError":
    """The one line for an address that cannot be served."""
    if getattr(err, "errno", None) == errno.EADDRINUSE:
        return LiveServerError(f"--port {port}: already in use on {host}; pass another --port (0: any free port)")
    return LiveServerError(f"--host {host} --port {port}: cannot listen there ({err})")


class LiveServerError(GeoAvatarError, OSError):
    """The player's address cannot be served (a port in use); the message names --host / --port."""


def _float32_bytes(values) -> bytes:
    if isinstance(values, torch.Tensor):
        values = values.detach().to("cpu", torch.float32).numpy()
    return np.ascontiguousarray(values, dtype="<f4").tobytes()


def vertex_message(vertices, sequence: int, code=None, capture_time: float | None = None) -> bytes:
    """The wire message of one posed mesh [V, 3] with its head pose code [6] when the hair follows the head: kind 1,
    or kind 3 carrying `capture_time` (when the mesh's own instant of sound was captured, Unix seconds) when given
    (module docstring)."""
    body = _float32_bytes(vertices) + (b"" if code is None else _float32_bytes(code))
    if capture_time is None:
        return HEADER.pack(KIND_VERTICES, sequence & 0xFFFFFFFF, time.time()) + body
    return HEADER.pack(KIND_SOUND_VERTICES, sequence & 0xFFFFFFFF, time.time()) + struct.pack("<d", capture_time) + body


def audio_message(samples, sequence: int, capture_time: float) -> bytes:
    """A page's microphone chunk as it travels (kind 2): samples [n] in [-1, 1] at AUDIO_RATE (tests, tools)."""
    pcm = np.rint(np.clip(np.asarray(samples, dtype=np.float64), -1.0, 1.0) * 32767).astype("<i2")
    return HEADER.pack(KIND_AUDIO, sequence & 0xFFFFFFFF, capture_time) + pcm.tobytes()


def read_audio_message(message: bytes) -> tuple[np.ndarray, float, int] | None:
    """(samples float32 [n] = int16 / 32768, capture time, sequence) of a kind-2 message; None when it is not one
    (another kind, too short, an odd number of sample bytes, a capture time that is not finite)."""
    if len(message) < HEADER.size or (len(message) - HEADER.size) % 2:
        return None
    kind, sequence, capture = HEADER.unpack_from(message)
    if kind != KIND_AUDIO or not np.isfinite(capture):
        return None
    samples = np.frombuffer(message, dtype="<i2", offset=HEADER.size).astype(np.float32) / 32768.0
    return samples, float(capture), int(sequence)


PENDING = 2  # meshes waiting per browser (see the module docstring)


class _Client:
    def __init__(self, socket):
        self.socket = socket
        self.pending: deque[tuple[bytes, float | None]] = deque()  # oldest first
        self.wake = asyncio.Event()


class LiveServer:
    def __init__(self, assets: PlayerAssets, host: str = "127.0.0.1", port: int = 8080,
                 on_edit: Callable[[dict], None] | None = None,
                 on_audio: Callable[[np.ndarray, float, int], None] | None = None,
                 on_microphone_error: Callable[[str], None] | None = None):
        self.files = {f"/{name}": (static_dir() / name).read_bytes() for name in PLAYER_FILES}
        self.files.update({f"/{name}": data for name, data in assets.files().items()})
        self.files["/"] = self.files["/index.html"]
        self.host, self.port, self.on_edit = host, port, on_edit
        self.on_audio, self.on_microphone_error = on_audio, on_microphone_error
        self.audio_chunks = 0  # microphone chunks handed to on_audio
        self.audio_ignored = 0  # malformed chunks, and those of a page that is not the microphone
        self._microphone: _Client | None = None  # the page whose sound is taken
        self.audio_error: BaseException | None = None  # the first exception of on_audio / on_microphone_error
        self.sequence = 0
        self.sent = 0  # meshes written to a browser (summed over browsers)
        self.dropped = 0  # meshes replaced before a browser took them
        self.latency_ms: list[float] = []
        self._clients: set[_Client] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server = None
        self._thread: threading.Thread | None = None
        self._edits = ThreadPoolExecutor(max_workers=1, thread_name_prefix="geoavatar-live-edit")
        self._audio = ThreadPoolExecutor(max_workers=1, thread_name_prefix="geoavatar-live-audio")  # in order

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else "::1" if self.host == "::" else self.host
        return f"http://[{host}]:{self.port}/" if ":" in host else f"http://{host}:{self.port}/"  # IPv6 in brackets

    @property
    def clients(self) -> int:
        return len(self._clients)

    def start(self) -> "LiveServer":
        ready = threading.Event()
        failure: list[BaseException] = []

        def run() -> None:
            self._loop = asyncio.new_event_loop()
            try:
                self._server = self._loop.run_until_complete(self._listen())
            except Exception as err:  # OSError, or a host name that cannot be encoded (UnicodeError, ValueError)
                failure.append(err)
                return
            finally:
                ready.set()  # whatever happened: start() must not wait for ever
            self._loop.run_until_complete(self._server.wait_closed())

        self._thread = threading.Thread(target=run, name="geoavatar-live", daemon=True)
        self._thread.start()
        ready.wait()
        if failure:
            raise _address_error(self.host, self.port, failure[0]) from failure[0]
        return self

    async def _listen(self):
        from websockets.asyncio.server import serve

        server = await serve(self._handle, self.host, self.port, process_request=self._http, compression=None,
                             max_size=1 << 16)
        self.port = server.sockets[0].getsockname()[1]
        return server

    def _http(self, connection, request):
        """Files for plain HTTP requests; None lets the websocket handshake of /ws go on."""
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        path = urlsplit(request.path).path
        if path == "/ws":
            return None
        body = self.files.get(path)
        if body is None:
            return connection.respond(404, f"{path}: not found\n")
        suffix = path[path.rfind("."):] if "." in path else ".html"
        headers = Headers({"Content-Type": CONTENT_TYPES.get(suffix, "application/octet-stream"),
                           "Content-Length": str(len(body)), "Cache-Control": "no-store", "Connection": "close"})
        return Response(200, "OK", headers, body)

    async def _handle(self, socket) -> None:
        client = _Client(socket)
        self._clients.add(client)
        writer = asyncio.create_task(self._write(client))
        try:
            async for message in socket:
                if isinstance(message, str):
                    self._text(client, message)
                else:
                    self._sound(client, message)
        except Exception:  # a browser that went away
            pass
        finally:
            self._clients.discard(client)
            if self._microphone is client:
                self._microphone = None
            writer.cancel()

    def _text(self, client: _Client, message: str) -> None:
        try:
            request = json.loads(message)
        except ValueError:
            return  # not ours: ignored
        if isinstance(request, dict) and request.get("type") == "microphone":
            # one page is the microphone: another page's refusal (a second tab) does not end it
            if self.on_microphone_error is not None and self._microphone in (None, client):
                self._loop.run_in_executor(self._audio, self._call, self.on_microphone_error,
                                           str(request.get("error", "")))
        elif self.on_edit is not None:
            self._loop.run_in_executor(self._edits, self.on_edit, request)

    def _sound(self, client: _Client, message: bytes) -> None:
        chunk = read_audio_message(message)
        if chunk is None or self.on_audio is None or self._microphone not in (None, client):
            self.audio_ignored += 1
            return
        self._microphone = client
        self.audio_chunks += 1
        self._loop.run_in_executor(self._audio, self._call, self.on_audio, *chunk)

    def _call(self, callback: Callable, *args) -> None:
        """A sound callback in the audio thread: its exception is printed and kept, not lost in a future."""
        try:
            callback(*args)
        except BaseException as err:  # noqa: BLE001 - reported, and handed to the caller through audio_error
            if self.audio_error is None:
                self.audio_error = err
            traceback.print_exc()

    async def _write(self, client: _Client) -> None:
        while True:
            await client.wake.wait()
            client.wake.clear()
            while client.pending:
                message, read_time = client.pending.popleft()
                try:
                    await client.socket.send(message)
                except Exception:
                    return
                self.sent += 1
                if read_time is not None:
                    self.latency_ms.append(1000.0 * (time.perf_counter() - read_time))

    def _publish(self, message: bytes, read_time: float | None) -> None:
        for client in self._clients:
            if len(client.pending) >= PENDING:
                client.pending.popleft()
                self.dropped += 1
            client.pending.append((message, read_time))
            client.wake.set()

    def send_vertices(self, vertices, read_time: float | None = None, code=None,
                      capture_time: float | None = None) -> None:
        """Send a posed mesh [V, 3] (and its head pose code [6] when the avatar's hair follows the head) to every
        connected browser (thread-safe; the newest PENDING wait per browser). capture_time: when the mesh's own
        instant of sound was captured (on on_audio's clock), which the page turns into its sound-to-picture
        latency."""
        if self._loop is None or self._loop.is_closed():
            return
        self.sequence += 1
        message = vertex_message(vertices, self.sequence, code, capture_time)
        self._loop.call_soon_threadsafe(self._publish, message, read_time)

    def wait_for_client(self, timeout_s: float) -> bool:
        """Wait until a browser is connected (tests, benchmarks); False on time-out."""
        deadline = time.monotonic() + timeout_s
        while not self._clients and time.monotonic() < deadline:
            time.sleep(0.05)
        return bool(self._clients)

    def stop(self) -> None:
        if self._loop is not None and self._server is not None and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._server.close)
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._edits.shutdown(wait=False, cancel_futures=True)
        self._audio.shutdown(wait=False, cancel_futures=True)


__all__ = ["AUDIO_RATE", "KIND_AUDIO", "KIND_SOUND_VERTICES", "KIND_VERTICES", "LiveServer", "LiveServerError",
           "audio_message", "check_address", "read_audio_message", "vertex_message"]
