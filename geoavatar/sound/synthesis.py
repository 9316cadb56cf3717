"""Text to speech, offline, through a speech synthesiser run as a separate program (`geoavatar speak --text`).

    sound = speak_text("Hello there", engine="auto", voice=None)      # Sound at 16 kHz; SoundError when none works

Engines (neither is a Python dependency: each is a program the user installs, run with subprocess):
    espeak-ng   GPL-3 (run as a separate process, never linked), ~130 languages: `--tts-voice fr`, `de`, `en-us`, ...;
                Debian / Ubuntu: `apt-get install espeak-ng`, macOS: `brew install espeak-ng`
    flite       BSD-like (CMU), English voices built in (`--tts-voice slt`, `kal`, `awb`, `rms`);
                `apt-get install flite`
`auto` takes espeak-ng when it is installed, else flite.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

from geoavatar.sound.track import RATE, Sound, SoundError, read_sound

ENGINES = ("espeak-ng", "flite")
INSTALL = "install one: `apt-get install espeak-ng` (or flite; macOS: `brew install espeak-ng`)"
TIMEOUT_SECONDS = 120


def find_engine(engine: str = "auto") -> str:
    """The program to run; SoundError naming --tts when it is not installed."""
    if engine not in ("auto", *ENGINES):
        raise SoundError(f"--tts must be auto, {' or '.join(ENGINES)}, got {engine!r}")
    for name in (ENGINES if engine == "auto" else (engine,)):
        if shutil.which(name):
            return name
    missing = "no offline speech synthesiser is installed" if engine == "auto" else f"--tts {engine}: not installed"
    raise SoundError(f"{missing}; {INSTALL}")


def _check_flite_voice(voice: str) -> None:
    """flite speaks in its default voice when it does not know the one asked (and exits 0): say so instead. A voice
    file (.flitevox) is flite's to read."""
    if voice.endswith(".flitevox") or Path(voice).is_file():
        return
    listed = subprocess.run(["flite", "-lv"], capture_output=True, text=True, timeout=TIMEOUT_SECONDS).stdout
    names = listed.split(":", 1)[-1].split()
    if names and voice not in names:
        raise SoundError(f"--tts-voice {voice}: not one of flite's voices ({', '.join(names)}); espeak-ng speaks "
                         "other languages (--tts espeak-ng)")


def _command(engine: str, text_file: Path, out: Path, voice: str | None) -> list[str]:
    if engine == "espeak-ng":
        return ["espeak-ng", "-w", str(out), "-f", str(text_file)] + (["-v", voice] if voice else [])
    return ["flite", "-f", str(text_file), "-o", str(out)] + (["-voice", voice] if voice else [])


def speak_text(text: str, engine: str = "auto", voice: str | None = None, rate: int = RATE) -> Sound:
    """The text spoken by the engine, read back at `rate`; SoundError (one line) when the text is empty or the engine
    fails."""
    if not text.strip():
        raise SoundError("--text is empty: give the words to say")
    program = find_engine(engine)
    if program == "flite" and voice:
        _check_flite_voice(voice)
    with tempfile.TemporaryDirectory(prefix="geoavatar-tts-") as folder:
        text_file, out = Path(folder) / "text.txt", Path(folder) / "speech.wav"
        text_file.write_text(text, encoding="utf-8")
        try:
            done = subprocess.run(_command(program, text_file, out, voice), capture_output=True, text=True,
                                  timeout=TIMEOUT_SECONDS)
        except subprocess.TimeoutExpired as err:
            raise SoundError(f"--text: {program} took longer than {TIMEOUT_SECONDS} s") from err
        if done.returncode != 0 or not out.is_file():
            detail = " ".join((done.stderr or done.stdout or "no message").split())[:200]
            raise SoundError(f"--text: {program} failed ({detail})" + (f"; is --tts-voice {voice} one of its voices?"
                                                                        if voice else ""))
        spoken = read_sound(out, rate, what=f"{program}'s speech")
    if not spoken.samples.any():
        raise SoundError(f"--text: {program} said nothing for {text.strip()[:40]!r}: give words it can speak")
    return spoken


__all__ = ["ENGINES", "find_engine", "speak_text"]
