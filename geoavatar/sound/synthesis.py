"""Text to speech, offline, through a speech synthesiser run as a separate program (`geoavatar speak --text`).

    sound = speak_text("Hello there", engine="auto", voice=None)      # Sound at 16 kHz; SoundError when none works

Engines (neither is a Python dependency: each is a program the user installs, run with subprocess):
    espeak-ng   GPL-3 (run as a separate process, never linked), ~130 languages: `--voice fr`, `de`, `en-us`, ...;
                Debian / Ubuntu: `apt-get install espeak-ng`, macOS: `brew install espeak-ng`
    flite       BSD-like (CMU), English voices built in (`--voice slt`, `kal`, `awb`, `rms`);
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
            raise SoundError(f"--text: {program} failed ({detail})" + (f"; is --voice {voice} one of its voices?"
                                                                        if voice else ""))
        return read_sound(out, rate, what=f"{program}'s speech")


__all__ = ["ENGINES", "find_engine", "speak_text"]
