"""VOICE layer: how a person's face moves when they speak, learned from the training frames of their own video.

    voice = train_voice(run)                          # train.py: sound -> expression and jaw (+ the idle motion)
    voice.save(run_dir); VoiceModel.load(run_dir)     # model.py: RUN/voice/voice.npz + voice.json (no pickle)
    face = voice.predict(sound, times)                # SpokenFace: expr [N, E], jaw [N, 3]
    voice.hearing("video")                            # the same voice, hearing loudness as the video's (model.py)
    VoiceStream(voice, fps).push(chunk)               # stream.py: the same, live, frame by frame
    speaking_params(face, idle.player(fps).take(N), identity)   # compose.py: the full head parameters

inputs.py (log-mel windows, normalisation, augmentation), net.py (the network), face.py (lip / upper-face vertices
of the head model), idle.py (head motion, gaze, blinks from the training frames). Below it: sound (decoding,
features), data (the dataset's sound), train (a run's parameters); above it: eval (eval/speech.py) and the speech
source of the animation layer.
"""

from geoavatar.voice.compose import speaking_params
from geoavatar.voice.config import VoiceConfig
from geoavatar.voice.model import LOUDNESS, SpokenFace, VoiceModel, VoiceModelError

__all__ = ["LOUDNESS", "SpokenFace", "VoiceConfig", "VoiceModel", "VoiceModelError", "speaking_params"]
