"""How the target is seen during manipulation: camera and localisation bias (docs/model.md §8)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from scissor_cli.scene.camera import Camera


@dataclass(frozen=True)
class Measurement:
    """How the target is seen: a camera (pixel noise + rounding) and a localisation bias.

    camera None is the ideal measurement: the true position exactly, no
    rounding, no random draws. bias_mm (2,) is a fixed per-trial offset of
    the image-based target localisation (drawn by the caller). noise_px
    overrides the camera's pixel noise σ.
    """

    camera: Optional[Camera] = None
    bias_mm: tuple[float, float] = (0.0, 0.0)
    noise_px: Optional[float] = None

    @property
    def ideal(self) -> bool:
        return self.camera is None and not np.any(self.bias_mm)

    @property
    def noise_mm(self) -> float:
        """σ (mm) of one measurement's random part at the layer: pixel noise and rounding (σ² + 1/12 px²); 0 without a camera."""
        if self.camera is None:
            return 0.0
        px = self.camera.pixel_noise_px if self.noise_px is None else self.noise_px
        return float(np.sqrt(px * px + 1.0 / 12.0) * np.max(self.camera.mm_per_pixel))

    def measure(self, true_position: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The measured target (2,) mm of the true target (2,) mm."""
        p = np.asarray(true_position, float)
        if self.camera is not None:
            p = self.camera.measure(p[None], rng, self.noise_px)[0]
        return p + np.asarray(self.bias_mm, float)
