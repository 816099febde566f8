"""Seeded draws consumed in a fixed layout: the k-th event of an instrument (a reading window,
a scan) or of the robot (a settling of its controller) always gets the k-th row, however many
rows are asked at a time, so a campaign computed at once and one run call by call give the
same data."""
from __future__ import annotations

import numpy as np


class NoiseBank:
    """Draws of one instrument, row k for its k-th event, produced in fixed blocks from a
    stream so that rows do not depend on how many are asked at a time."""
    BLOCK = 4096

    def __init__(self, rng: np.random.Generator, draw):
        self.rng, self.draw, self.rows = rng, draw, None

    def take(self, start: int, stop: int) -> np.ndarray:
        while self.rows is None or self.rows.shape[0] < stop:
            block = self.draw(self.rng, self.BLOCK)
            self.rows = block if self.rows is None else np.concatenate([self.rows, block])
        return self.rows[start:stop]


def quantised_u(noise: float, resolution: float) -> float:
    """The standard uncertainty of a reading with white noise of std ``noise`` shown to steps of
    ``resolution`` (same units): the rounding error is uniform over one step, variance
    step^2 / 12 (GUM F.2.2.1), independent of the noise."""
    return float(np.hypot(noise, resolution / np.sqrt(12)))
