"""`geoavatar speak RUN (--audio FILE | --text "..." | --microphone)`: the avatar says something new.

The front end of the animation layer's speech sources (animation/sources/speech.py: the run's voice model, learned
from its own video by `geoavatar train` / `geoavatar voice`, makes each frame's expression and jaw; the person's idle
motion from their training frames moves the head, the eyes and the brows) and its sinks:

    --audio FILE       any sound or video file PyAV reads (wav, mp3, m4a, a video's sound)
    --text "..."       spoken first by an offline speech synthesiser (espeak-ng or flite, run as a separate program;
                       sound/synthesis.py), --tts-voice chooses its voice (espeak-ng: fr, de, en-us, ...)
    --microphone       the browser's microphone, live (with --view: the page captures it, animation/sources/speech.py)
    --live             play --audio as a live source in real time, as a microphone would deliver it

Outputs: --out FILE.mp4 (the avatar with the sound, one frame per 1/fps of it; default RUN/videos/speak_<name>.mp4),
--view (the browser player: the clip with its sound, or live meshes streamed as the sound arrives).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

from geoavatar.animation.play import play
from geoavatar.animation.sinks.mp4 import Mp4Sink
from geoavatar.animation.sources.speech import (LiveSpeech, MicrophoneSound, RealTimeSound, SpeechFrames,
                                                avatar_camera)
from geoavatar.apps.common import (VIDEO_DIR, RunPath, check_resolution, check_threads, default_output,
                                   serve_until_interrupted, torch_threads)
from geoavatar.errors import GeoAvatarError, OptionError
from geoavatar.sound import RATE, Sound, read_sound
from geoavatar.train.checkpoint import LoadedRun, open_run
from geoavatar.voice import VoiceModel
from geoavatar.voice.model import loudness_tag

PLAYBACK_RATE = 24000  # the sound the mp4 and the player carry: speech at full quality, half of CD's size


def _check_options(audio, text, microphone, live, view, out, fps, max_seconds, loudness) -> None:
    if sum(x is not None and x is not False for x in (audio, text, microphone or None)) != 1:
        raise OptionError("give one thing to say: --audio FILE, --text \"...\" or --microphone")
    if loudness == "video" and text is not None:
        raise OptionError("--loudness video is for a recording made as the video was; --text's synthesised voice "
                          "has a loudness of its own")
    if microphone and not view:
        raise OptionError("--microphone needs --view: the browser page is the microphone and shows the avatar")
    if live and audio is None:
        raise OptionError("--live plays --audio FILE as a live source; --microphone is live by itself")
    if (live or microphone) and not view and out is None:
        raise OptionError("nothing to show: pass --view and/or --out FILE.mp4")
    if fps <= 0:
        raise OptionError(f"--fps must be positive, got {fps}")
    if max_seconds is not None and max_seconds <= 0:
        raise OptionError(f"--max-seconds must be positive, got {max_seconds}")


def spoken_sound(audio: Path | None, text: str | None = None, tts: str = "auto",
                 tts_voice: str | None = None) -> tuple[Sound, Sound, str]:
    """(the sound at the model's rate, the same for playback, its name) of --audio or --text."""
    if audio is not None:
        return (read_sound(audio, RATE, what="--audio"), read_sound(audio, PLAYBACK_RATE, what="--audio"),
                Path(audio).stem)
    from geoavatar.sound.synthesis import speak_text

    from geoavatar.sound.track import resample

    spoken = speak_text(text, tts, tts_voice, PLAYBACK_RATE)
    return resample(spoken, RATE), spoken, "text"


def speak_clip(run: LoadedRun, voice: VoiceModel, sound: Sound, playback: Sound, out: Path | None = None,
               clip_name: str | None = None, fps: float = 25.0, seed: int = 0, resolution: int | None = None,
               data: Path | None = None, backend: str = "auto", progress: bool = True, threads: int = 1):
    """The avatar saying `sound` (with `playback` as its sound), posed once for each of: the mp4 `out`, and the
    browser player's clip named `clip_name`; returns (the mp4's frame count, the clip or None)."""
    from geoavatar.animation.sinks.web import WebClip

    source = SpeechFrames(run, voice, sound, fps, playback, seed)
    mp4 = (Mp4Sink(run, out, fps, avatar_camera(run, data, resolution), backend=backend, audio=source.audio)
           if out is not None else None)
    clip = (WebClip(run, source.fps, f"speech {clip_name}{loudness_tag(voice.loudness, label=True)}",
                    [run.info.timesteps["all"][0]], data, audio=source.audio) if clip_name is not None else None)
    with torch_threads(threads):
        play(run, source, [sink for sink in (mp4, clip) if sink is not None], progress=progress, desc="speak")
    return (mp4.frames if mp4 is not None else 0), clip


def _serve_clip(clip, host: str, port: int, serve_forever: bool) -> None:
    """The browser player of the speech clip with its sound, until Ctrl-C."""
    from geoavatar.web.live import LiveServer

    server = LiveServer(clip.assets(), host, port).start()
    print(f"GeoAvatar player: {server.url}  (press Play for the sound; Ctrl-C stops)", flush=True)
    serve_until_interrupted(server, serve_forever)


def speak_live(run: LoadedRun, voice: VoiceModel, sound_input, fps: float, seed: int, viewer=None,
               out: Path | None = None, resolution: int | None = None, data: Path | None = None,
               backend: str = "auto", max_seconds: float | None = None, status: bool = True, audio=None):
    """A live sound through the voice model into the browser (`viewer`) and / or an mp4; returns the LiveSpeech
    source (its stats: frames, FPS, drops, sound-to-picture latency)."""
    from geoavatar.animation.sinks.browser import LiveStream

    source = LiveSpeech(run, voice, sound_input, fps, seed, max_seconds)
    sinks = []
    if viewer is not None:
        sinks.append(LiveStream(viewer, run, source))
    if out is not None:
        sinks.append(Mp4Sink(run, out, fps, avatar_camera(run, data, resolution), backend=backend,
                             check_values=False, audio=audio))
    play(run, source, sinks, status=status)
    return source


def speak(
    run: RunPath,
    audio: Optional[Path] = None,
    text: Optional[str] = None,
    microphone: bool = False,
    out: Optional[Path] = None,
    view: bool = False,
    live: bool = False,
    tts: Literal["auto", "espeak-ng", "flite"] = "auto",
    tts_voice: Optional[str] = None,
    fps: float = 25.0,
    seed: int = 0,
    resolution: Optional[int] = None,
    max_seconds: Optional[float] = None,
    host: str = "127.0.0.1",
    port: int = 8080,
    data: Optional[Path] = None,
    device: str = "auto",
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto",
    flame_dir: Optional[Path] = None,
    progress: bool = True,
    status: bool = True,
    threads: int = 1,
    serve_forever: bool = True,
    loudness: Literal["own", "video"] = "own",
) -> int:
    """Make the avatar say something new: a sound file, a text (offline speech synthesis) or a live microphone, through
    the voice model the run learned from its own video (`geoavatar train` on a video with speech, or `geoavatar
    voice RUN`). The head moves, the eyes blink and look around as the person did in their video.

    Args:
        run: Run folder written by `geoavatar train`, with its voice model (RUN/voice/).
        audio: A sound or video file to say (wav, mp3, m4a, mp4, ...).
        text: Words to say, spoken first by an offline speech synthesiser (--tts).
        microphone: Speak live into the browser's microphone (needs --view; the page asks for it).
        out: The mp4 to write (the avatar with the sound; default RUN/videos/speak_<name>.mp4 unless --view,
            speak_<name>@video-loudness.mp4 with --loudness video).
        view: Show it in the browser player: the clip with its sound, or live.
        live: Play --audio as a live source in real time (the microphone's path, for a machine without one).
        tts: The speech synthesiser for --text: auto (espeak-ng if installed, else flite), espeak-ng or flite.
        tts_voice: The synthesiser's voice or language (espeak-ng: en-us, fr, de, ...; flite: slt, kal, awb, rms).
        fps: Frames per second of the avatar (one frame per 1/fps of sound).
        seed: Seed of the idle motion (which stretches of the person's head motion and blinks are played).
        resolution: Longer side of the mp4's frames (default: the run's training resolution).
        max_seconds: Live: stop after this much sound.
        host: Address of the browser player (--view).
        port: Port of the browser player (--view; 0: any free port).
        data: The run's dataset folder, when it moved since training (the camera is read from it).
        device: auto (CUDA when available, else CPU), cpu, cuda or cuda:N.
        backend: Rasterizer: auto, cpu, torch or gsplat.
        flame_dir: Folder with your FLAME model files (FLAME avatars only).
        progress: Show a progress bar (a file).
        status: Live: print a status line (FPS, drops, latency) about once a second.
        threads: CPU threads of the rendering loop (1: a frame's tensors are small).
        serve_forever: --view of a file: keep serving until Ctrl-C (off: start, print the address and stop).
        loudness: How the sound is normalised before the voice hears it: own (by its own speech: any voice, any
            microphone, any level moves the mouth) or video (by the video's speech: for a recording made as the
            video was, same microphone and distance, where speaking louder or softer opens the mouth more or less,
            and the mean mouth follows the sound's level against the video's as the person's did, within 6 dB; a
            microphone then keeps the video's statistics and follows the level of its last 10 s).
    """
    _check_options(audio, text, microphone, live, view, out, fps, max_seconds, loudness)
    check_threads(threads)
    check_resolution(resolution)
    loaded = open_run(run, device, flame_dir)
    voice = VoiceModel.load(loaded.info.run_dir).hearing(loudness)  # VoiceModelError: how to get one
    if microphone or live:
        return _speak_live(loaded, voice, audio, microphone, out, view, fps, seed, resolution, max_seconds, host,
                           port, data, backend, status)
    sound, playback, name = spoken_sound(audio, text, tts, tts_voice)
    target = (out if out is not None or view else
              default_output(loaded, VIDEO_DIR, f"speak_{name}{loudness_tag(loudness)}.mp4"))  # beside own's
    count, clip = speak_clip(loaded, voice, sound, playback, target, name if view else None, fps, seed, resolution,
                             data, backend, progress, threads)
    if target is not None:
        print(f"wrote {target} ({count} frames at {fps:g} fps, {sound.seconds:.1f} s of sound)")
    if clip is not None:
        _serve_clip(clip, host, port, serve_forever)
    return 0


def _speak_live(run, voice, audio, microphone, out, view, fps, seed, resolution, max_seconds, host, port, data,
                backend, status) -> int:
    """--microphone or --audio --live: the live source into the browser and / or an mp4."""
    from geoavatar.apps.view import start_viewer

    sound, playback, _ = (None, None, None) if microphone else spoken_sound(audio)  # the mp4 carries the playback
    sound_input = MicrophoneSound() if microphone else RealTimeSound(sound)
    viewer = None
    if view:
        callbacks = ({"on_audio": sound_input.on_audio, "on_microphone_error": sound_input.on_error}
                     if microphone else {})
        try:
            viewer = start_viewer(run, host, port, expr_sliders=0, data=data, live="speak" if microphone else True,
                                  **callbacks)
        except (ImportError, OSError) as err:
            raise GeoAvatarError(f"cannot start the viewer: {err}") from err
        print(f"GeoAvatar live viewer: {viewer.url}" + ("  (allow the microphone in the page; Ctrl-C stops)"
                                                        if microphone else ""), flush=True)
    try:
        source = speak_live(run, voice, sound_input, fps, seed, viewer, out, resolution, data, backend, max_seconds,
                            status, playback)
    except KeyboardInterrupt:  # before the first frame (play keeps what a live source made once it began)
        return 0
    finally:
        if viewer is not None:
            viewer.stop()
    print(f"speak: {source.stats.summary()}" + (f"; wrote {out}" if out is not None else "")
          + (f"; {viewer.summary()}" if viewer is not None else ""))
    return 0


__all__ = ["PLAYBACK_RATE", "speak", "speak_clip", "speak_live", "spoken_sound"]
