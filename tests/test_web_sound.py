"""The web player with sound: a clip's sound track (audio.wav, the page's clock: frame = floor(audio time * fps)),
autoplay refused (a status line, paused on frame 0), and the page as a live microphone for `speak` (getUserMedia,
resampled to 16 kHz in an AudioWorklet, 20 ms chunks over the websocket to LiveServer's on_audio; the capture time
echoed back with the meshes as the page's sound-to-picture latency; a page without a microphone says so).

The browser tests drive Debian's chromium with Playwright (geoavatar/web/browser.py) on a 300-splat OpenHead avatar at
64-128 px (tests/web_fixtures.small_player: no trained run); the microphone is Chromium's fake device playing a WAV
written here (a 440 Hz tone switched on and off every 0.25 s). The resampler itself runs in node."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import time
import types
import wave
from pathlib import Path

import numpy as np
import pytest

from web_fixtures import on_off_tone, small_player
from geoavatar.web import pack
from geoavatar.web.browser import (AUTOPLAY, REFUSE_AUTOPLAY, browser_missing, chromium_page, fake_microphone,
                                   static_server, wait_drawn)
from geoavatar.web.live import (AUDIO_RATE, KIND_SOUND_VERTICES, LiveServer, audio_message, read_audio_message,
                                vertex_message)

FPS, FRAMES, SOUND_SECONDS, SOUND_RATE = 10.0, 30, 2.0, 22050  # the clip outlasts its sound: it loops at 2 s
MICROPHONE_JS = Path(__file__).resolve().parents[1] / "web" / "src" / "microphone.js"
browser = pytest.mark.skipif(browser_missing() is not None, reason=f"browser tests: {browser_missing()}")
AUDIO = "document.getElementById('sound')"
# The sound's clock and the frame shown, read in the next animation frame after the player's own (whose callback was
# asked for first): what is on screen at that moment, however long the page was busy before (software WebGL).
SHOWN = (f"() => new Promise((done) => requestAnimationFrame(() => done([{AUDIO}.currentTime, "
         "window.geoavatar.player.frame])))")


@pytest.fixture(scope="module")
def sound():
    return on_off_tone(SOUND_SECONDS, SOUND_RATE)


@pytest.fixture(scope="module")
def folder(sound, tmp_path_factory):
    assets, _ = small_player(FRAMES, FPS, size=96, audio=sound)
    return pack.write_player_folder(tmp_path_factory.mktemp("sound") / "web", assets)


@pytest.fixture(scope="module")
def speaker():
    """A one-frame live "speak" player and its mesh [V, 3]."""
    assets, vertices = small_player(1, live="speak")
    return assets, vertices[0]


def test_a_sound_track_is_written_as_16_bit_mono_wav(sound, folder):
    manifest = json.loads((folder / pack.MANIFEST).read_text())
    assert manifest["clip"]["audio"] == {"file": pack.AUDIO_FILE, "rate": SOUND_RATE, "seconds": SOUND_SECONDS}
    assert manifest["format"] == pack.FORMAT_VERSION == 2  # compatible: an old folder has no clip.audio and plays
    with wave.open(str(folder / pack.AUDIO_FILE), "rb") as wav:
        assert (wav.getnchannels(), wav.getsampwidth(), wav.getframerate()) == (1, 2, SOUND_RATE)
        assert wav.getnframes() == len(sound.samples) == SOUND_SECONDS * SOUND_RATE
    back = pack.read_wav((folder / pack.AUDIO_FILE).read_bytes())
    assert np.abs(back.samples - sound.samples).max() <= 0.5 / pack.PCM_MAX + 1e-7
    assert sorted(p.name for p in folder.iterdir()) == sorted([*pack.PLAYER_FILES, pack.MANIFEST, pack.AVATAR_FILE,
                                                               pack.CLIP_FILE, pack.AUDIO_FILE])


def test_any_sound_with_samples_and_rate_is_taken_and_bad_ones_are_refused():
    loud = types.SimpleNamespace(samples=np.array([0.0, 2.0, -3.0, 0.5]), rate=8000.0)  # geoavatar.sound's Sound too
    back = pack.read_wav(pack.wav_bytes(loud))
    assert back.rate == 8000 and back.samples.tolist() == pytest.approx([0.0, 1.0, -1.0, 0.5], abs=1e-4)  # clipped
    for bad, words in [(types.SimpleNamespace(samples=np.zeros((10, 2)), rate=16000), "mono"),
                       (types.SimpleNamespace(samples=np.zeros(0), rate=16000), "mono"),
                       (types.SimpleNamespace(samples=np.array([0.0, np.nan]), rate=16000), "NaN"),
                       (types.SimpleNamespace(samples=np.zeros(4), rate=0), "rate"),
                       (types.SimpleNamespace(samples=np.zeros(4), rate=16000.5), "rate")]:
        with pytest.raises(ValueError, match=words):
            pack.wav_bytes(bad)


@browser
def test_the_clip_plays_in_step_with_its_sound(folder):
    console: list[str] = []
    with static_server(folder) as url, chromium_page(128, 128, console=console, args=AUTOPLAY) as page:
        page.goto(url + "index.html")
        page.wait_for_function(f"window.geoavatar?.stats.ready && !{AUDIO}.paused && {AUDIO}.currentTime > 0.1",
                               timeout=120_000)
        page.evaluate(f"{AUDIO}.currentTime = 0.25")
        samples = []
        for _ in range(5):
            time.sleep(0.2)
            samples.append(page.evaluate(SHOWN))
        times = [t for t, _ in samples]
        assert all(b > a for a, b in zip(times, times[1:])), samples  # the sound's clock runs
        assert times[-1] - times[0] > 0.5, samples
        for t, frame in samples:
            assert abs(math.floor(t * FPS) - frame) <= 1, samples
        stats = page.evaluate("window.geoavatar.stats")
        assert stats["audioFrame"] == math.floor(stats["audioTime"] * FPS + 1e-4) and not stats["audioBlocked"]
        page.evaluate(f"{AUDIO}.currentTime = 0.05")  # back: a clock of the page's own would never go there
        page.wait_for_function("window.geoavatar.player.frame <= 1", timeout=10_000)

        # the sound is the clock: move it and the picture follows; the clip loops where the sound ends (2 s: frame
        # 20 of 30), restarting the sound
        page.evaluate("() => { window.seen = []; const look = () => { window.seen.push(window.geoavatar.player.frame);"
                      " requestAnimationFrame(look); }; look(); }")
        page.evaluate(f"{AUDIO}.currentTime = 1.55")
        page.wait_for_function("window.seen.includes(15) && window.geoavatar.player.frame < 3", timeout=10_000)
        seen = page.evaluate("window.seen")
        assert max(seen) <= SOUND_SECONDS * FPS - 1 and max(seen) >= 18, seen
        assert page.evaluate(f"!{AUDIO}.paused")

        page.click("#play")  # pause: the sound stops with the picture
        paused_at = page.evaluate(f"[{AUDIO}.currentTime, window.geoavatar.player.frame, {AUDIO}.paused]")
        time.sleep(0.3)
        assert page.evaluate(f"[{AUDIO}.currentTime, window.geoavatar.player.frame, {AUDIO}.paused]") == paused_at
        assert paused_at[2] and paused_at[1] == math.floor(paused_at[0] * FPS + 1e-4)
        page.evaluate("delete document.body.dataset.drawnFrame")
        page.fill("#scrub", "12")  # scrub: the sound moves to the frame
        page.dispatch_event("#scrub", "input")
        wait_drawn(page, 12)
        assert page.evaluate(f"{AUDIO}.currentTime") == pytest.approx(1.2, abs=1e-3)
        page.click("#play")  # plays on from there
        page.wait_for_function(f"!{AUDIO}.paused && window.geoavatar.player.frame >= 13", timeout=10_000)
        t, frame = page.evaluate(SHOWN)
        assert 1.2 < t < 2.0 and abs(math.floor(t * FPS) - frame) <= 1
    assert not [line for line in console if line.startswith(("error", "pageerror"))], console


@browser
def test_a_refused_autoplay_waits_on_frame_0_with_a_status_line(folder):
    with static_server(folder) as url, chromium_page(128, 128, args=REFUSE_AUTOPLAY) as page:
        # Nothing may be evaluated in the page before it has tried: Playwright evaluates as a user gesture, after
        # which the browser lets the sound start; the page's console line says when it was refused.
        with page.expect_console_message(lambda line: "press Play for sound" in line.text, timeout=120_000):
            page.goto(url + "index.html?frame=4")  # would play from frame 4
        assert page.inner_text("#live-status") == "press Play for sound"
        wait_drawn(page, 0)
        time.sleep(0.5)
        state = page.evaluate(f"[window.geoavatar.player.frame, window.geoavatar.player.playing, {AUDIO}.paused, "
                              f"{AUDIO}.currentTime, window.geoavatar.stats.audioBlocked, "
                              "document.getElementById('play').textContent]")
        assert state == [0, False, True, 0, True, "Play"], state
        page.click("#play")  # a click lets the sound start
        page.wait_for_function(f"!{AUDIO}.paused && window.geoavatar.player.frame >= 3", timeout=10_000)
        assert page.inner_text("#live-status") == "" and not page.evaluate("window.geoavatar.stats.audioBlocked")

        page.goto(url + "index.html?frame=7&paused=1&view=dataset")  # deep links hold with sound
        wait_drawn(page, 7)
        assert page.evaluate(f"[{AUDIO}.paused, {AUDIO}.currentTime]") == [True, pytest.approx(0.7, abs=1e-3)]
        assert page.inner_text("#live-status") == ""


def test_the_server_takes_one_pages_sound_in_order():
    """Without a browser: kind-2 chunks from a websocket reach on_audio in order, as float32 at 16 kHz with their
    capture times; malformed ones and a second page's are dropped and counted; the microphone page's error message
    reaches on_microphone_error, a second page's does not; a mesh with a capture time travels as kind 3."""
    from websockets.sync.client import connect

    assets, vertices = small_player(1, live="speak")
    got, errors = [], []
    server = LiveServer(assets, port=0, on_audio=lambda *chunk: got.append(chunk),
                        on_microphone_error=errors.append).start()
    try:
        ws = server.url.replace("http", "ws") + "ws"
        with connect(ws) as first, connect(ws) as second:
            tone = 0.5 * np.sin(np.arange(640) / 5.0)
            first.send(audio_message(tone[:320], 0, 1000.5))
            second.send(audio_message(tone[:320], 0, 1000.5))  # not the microphone: dropped
            first.send(audio_message(tone[:3], 1, 1000.52)[:-1])  # odd length: dropped
            first.send(audio_message(tone[320:], 2, 1000.54))
            second.send(json.dumps({"type": "microphone", "error": "NotAllowedError: another tab"}))  # not the mic
            first.send(json.dumps({"type": "microphone", "error": "NotAllowedError: Permission denied"}))
            deadline = time.monotonic() + 10
            while (len(got) < 2 or not errors) and time.monotonic() < deadline:
                time.sleep(0.02)
        assert [(seq, capture) for _, capture, seq in got] == [(0, 1000.5), (2, 1000.54)]
        samples = np.concatenate([s for s, _, _ in got])
        assert samples.dtype == np.float32 and np.abs(samples - tone).max() < 1e-4
        assert errors == ["NotAllowedError: Permission denied"] and server.audio_ignored == 2
        assert server.audio_chunks == 2
    finally:
        server.stop()
    message = vertex_message(vertices[0], 7, capture_time=1234.25)
    assert message[:4] == KIND_SOUND_VERTICES.to_bytes(4, "little") and len(message) == 24 + vertices[0].nbytes
    assert np.frombuffer(message[16:24], "<f8")[0] == 1234.25
    assert read_audio_message(message) is None and read_audio_message(b"\x02\x00") is None


@browser
def test_the_page_is_a_16_khz_microphone(speaker, tmp_path):
    """Chromium's fake microphone plays the tone; the server gets it at real-time rate, 16 kHz, with the tone's pitch
    and on/off envelope; meshes sent back with the chunks' capture times give the page's sound-to-picture latency."""
    assets, mesh = speaker
    tone = on_off_tone(3.0, 16000)  # the fake device loops it; 0.5 s periods, so a loop keeps the rhythm
    wav = tmp_path / "microphone.wav"
    wav.write_bytes(pack.wav_bytes(tone))
    chunks = []  # (samples, capture time, sequence, received at)

    def on_audio(samples, capture, sequence):
        chunks.append((samples, capture, sequence, time.time()))
        if sequence % 2:  # a mesh every 40 ms, as a voice model at 25 fps would pose
            server.send_vertices(mesh, None, None, capture_time=capture)

    server = LiveServer(assets, port=0, on_audio=on_audio).start()
    try:
        with chromium_page(96, 96, args=fake_microphone(wav)) as page:
            page.goto(server.url)
            deadline = time.monotonic() + 60
            while not chunks and time.monotonic() < deadline:
                time.sleep(0.05)
            assert chunks, page.evaluate("window.geoavatar?.stats")
            time.sleep(2.5)
            received = list(chunks)
            page.wait_for_function("window.geoavatar.stats.soundToPicture.count >= 10", timeout=10_000)
            stats = page.evaluate("window.geoavatar.stats")
            status = page.inner_text("#live-status")
    finally:
        server.stop()
    assert status == "microphone on" and stats["microphoneError"] is None
    assert [c[2] for c in received] == list(range(len(received)))  # every chunk, in order
    assert {len(c[0]) for c in received} == {AUDIO_RATE // 50}  # 20 ms each
    count = len(received) - 1
    # Capture times 20 ms apart. The page maps the audio clock to its own by the smallest delivery delay seen so far,
    # which the first chunks (delivered late while the page starts) overstate: their capture times come out up to
    # ~0.1 s late (a fresh clone's run: 2.52 s over 2.60 s of chunks). So the spacing, and the span of the later half.
    captures = np.array([c[1] for c in received])
    assert np.median(np.diff(captures)) == pytest.approx(0.02, abs=5e-4)
    later = captures[len(captures) // 2:]
    assert later[-1] - later[0] == pytest.approx((len(later) - 1) / 50, rel=0.03)
    arrived = received[-1][3] - received[0][3]
    assert arrived == pytest.approx(count / 50, rel=0.15)  # real time, not faster, not slower
    assert abs(received[-1][3] - received[-1][1]) < 1.0  # the page's clock is the server's (one machine)

    samples = np.concatenate([c[0] for c in received])
    spectrum = np.abs(np.fft.rfft(samples * np.hanning(len(samples))))
    assert np.fft.rfftfreq(len(samples), 1 / AUDIO_RATE)[spectrum.argmax()] == pytest.approx(440.0, abs=3.0)
    envelope = np.sqrt(np.mean(np.stack([c[0] for c in received]) ** 2, axis=1))  # RMS per chunk [C]
    period = np.concatenate([tone.samples, tone.samples])
    best = max(np.corrcoef(envelope, np.sqrt(np.mean(
        np.resize(np.roll(period, -lag), len(envelope) * 320).reshape(-1, 320) ** 2, axis=1)))[0, 1]
        for lag in range(0, 8000, 80))  # every 5 ms of the 0.5 s on/off period
    assert best > 0.9, best
    assert 0.2 < envelope.max() < 0.5  # the tone's RMS (0.35): no gain control

    latency = stats["soundToPicture"]
    assert latency["count"] >= 10 and 0 < latency["p50"] <= latency["p95"] < 2000, latency


@browser
def test_a_page_without_a_microphone_says_so(speaker):
    errors = []
    server = LiveServer(speaker[0], port=0, on_audio=lambda *chunk: None, on_microphone_error=errors.append).start()
    try:
        with chromium_page(96, 96) as page:  # no fake device: Chromium finds no microphone
            page.goto(server.url)
            deadline = time.monotonic() + 60
            while not errors and time.monotonic() < deadline:
                time.sleep(0.05)
            stats = page.evaluate("window.geoavatar.stats")
            server.stop()  # the command ends on the error: the page's line stays once its socket closes
            page.wait_for_function("window.geoavatar.player.live.socket.readyState === 3", timeout=10_000)
            status = page.inner_text("#live-status")
    finally:
        server.stop()
    assert len(errors) == 1 and errors[0].startswith("microphone: ") and "\n" not in errors[0], errors
    assert status == errors[0] == stats["microphoneError"] and stats["microphoneChunks"] == 0


NODE_SCRIPT = """
import { WORKLET_SOURCE } from %s;
let text = "";
for await (const chunk of process.stdin) text += chunk;
const job = JSON.parse(text);
let Processor;
const clock = {};
class Base { constructor() { this.port = { sent: [], postMessage(m) { this.sent.push(m); } }; } }
new Function("AudioWorkletProcessor", "registerProcessor", "sampleRate", "clock",
  "let currentTime = 0; clock.set = (t) => { currentTime = t; };" + WORKLET_SOURCE)(
  Base, (name, cls) => { Processor = cls; }, job.rate, clock);
const processor = new Processor({ processorOptions: {} });
const input = Float64Array.from(job.input);
for (let start = 0; start + 128 <= input.length; start += 128) {
  clock.set(start / job.rate);
  const quantum = Float32Array.from(input.subarray(start, start + 128));
  processor.process([[quantum, quantum]]);  // stereo in: mixed to mono
}
const sent = processor.port.sent;
process.stdout.write(JSON.stringify({ samples: sent.flatMap((m) => Array.from(new Int16Array(m.samples))),
  times: sent.map((m) => m.time), sizes: sent.map((m) => new Int16Array(m.samples).length) }));
"""


@pytest.mark.skipif(shutil.which("node") is None, reason="node is not installed (Node 20: the page's resampler)")
@pytest.mark.parametrize("rate", [48000, 44100])
def test_the_worklet_resamples_to_16_khz_without_aliasing(rate):
    """The AudioWorklet's resampler (web/src/microphone.js) in node: 440 Hz and 7 kHz tones keep their amplitude,
    12 kHz (which 16 kHz would alias to 4 kHz) and 9.5 kHz (to 6.5 kHz) are gone, 20 ms chunks carry the context time
    of their last sample."""
    t = np.arange(rate) / rate  # 1 s
    signal = (0.4 * np.sin(2 * np.pi * 440 * t) + 0.3 * (np.sin(2 * np.pi * 12000 * t) + np.sin(2 * np.pi * 9500 * t))
              + 0.1 * np.sin(2 * np.pi * 7000 * t))
    script = NODE_SCRIPT % json.dumps(MICROPHONE_JS.as_uri())
    done = subprocess.run(["node", "--input-type=module", "-e", script], input=json.dumps({"rate": rate,
                          "input": signal.tolist()}), capture_output=True, text=True, timeout=60, check=True)
    out = json.loads(done.stdout)
    assert set(out["sizes"]) == {320} and len(out["sizes"]) >= 49
    y = np.asarray(out["samples"], dtype=np.float64) / 32767
    k = np.arange(len(y))[200:-200]  # away from the start

    def amplitude(frequency: float) -> float:
        return 2 * abs(np.mean(y[k] * np.exp(-2j * np.pi * frequency * k / 16000)))

    assert amplitude(440) == pytest.approx(0.4, rel=0.01)
    assert amplitude(7000) == pytest.approx(0.1, rel=0.06)  # flat to the features' top band (7.6 kHz), as a file's
    assert amplitude(4000) < 0.001 and amplitude(6500) < 0.003  # the aliases, below -40 dB
    expected = (np.arange(1, len(out["times"]) + 1) * 320 - 1) / 16000  # the chunk's last sample
    np.testing.assert_allclose(out["times"], expected, atol=1e-6)
