"""Sound, low in the tree beside io and imaging: one reading path (PyAV, resampled once to 16 kHz mono), the log-mel
features the voice model hears (the same numbers for a file and a live stream) and where speech is (Silero VAD).

    sound = read_sound("talk.mp4")                 # track.py: Sound(samples [n] float32, rate, start); SoundError
    mel = log_mel(sound)                           # features.py: [F, 40] at 100 frames a second
    speech_activity(sound).speech_seconds          # activity.py
"""

from geoavatar.sound.features import FRAME_RATE, HOP, LogMelStream, N_MELS, N_MFCC, frame_energy, log_mel, mfcc
from geoavatar.sound.track import (RATE, Sound, SoundError, has_sound_track, read_sound, to_pcm16, video_frames,
                                   write_wav)

__all__ = ["FRAME_RATE", "HOP", "LogMelStream", "N_MELS", "N_MFCC", "RATE", "Sound", "SoundError", "frame_energy",
           "has_sound_track", "log_mel", "mfcc", "read_sound", "to_pcm16", "video_frames", "write_wav"]
