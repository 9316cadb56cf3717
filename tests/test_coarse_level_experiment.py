"""EXPERIMENT (reverted): the photometric fit's image term against depth at a coarse level rendered at its own size
with mass-conserving opacity, beside the supersampled render. Run with -s to see the curves."""
import numpy as np
import test_photometric as T
from test_photometric import head  # noqa: F401


def _curve(head, size, supersample, mass):
    truth = T._truth(head, 3)
    frames = T._render_frames(head, truth, T.PATTERN_SIZE)
    orig = T.render_at
    if mass:
        T.render_at = lambda *a, **k: orig(*a, **{**k, "mass_of": T.PATTERN_SIZE // size})
    try:
        shifts = (-20, -10, -5, -2, 0, 2, 5, 10, 20)
        losses = T.depth_response(head, truth, frames, size, [1e-3 * d for d in shifts], supersample)
    finally:
        T.render_at = orig
    print(size, "supersampled" if supersample else "mass-conserving", [f"{d}:{v:.5f}" for d, v in zip(shifts, losses)],
          "least at", shifts[int(np.argmin(losses))])
    return shifts[int(np.argmin(losses))]


def test_coarse_level_curves(head):
    for size in (T.PATTERN_SIZE // 2, T.PATTERN_SIZE // 4):
        assert _curve(head, size, True, False) == 0
        _curve(head, size, False, True)
