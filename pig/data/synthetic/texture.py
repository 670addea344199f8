"""Procedural albedo of the synthetic subject, evaluated at canonical (rest-pose) surface points.

Detail lives in the function, not the mesh, so it is as fine as the pixels that sample it; it is
ground truth for the appearance the avatar's colour decoder (paper Eq. 7) has to learn.
"""
from __future__ import annotations

import numpy as np

_TABLE_SIZE = 1024


class ValueNoise:
    """Seeded 3D value noise: random values on an integer lattice, smoothly interpolated, in [0, 1]."""

    def __init__(self, seed: int):
        self.table = np.random.default_rng(seed).random(_TABLE_SIZE)

    def _lattice(self, cells: np.ndarray) -> np.ndarray:
        # Large odd multipliers scatter neighbouring cells over the table (a spatial hash).
        h = cells[..., 0] * 73856093 ^ cells[..., 1] * 19349663 ^ cells[..., 2] * 83492791
        return self.table[np.mod(h, _TABLE_SIZE)]

    def __call__(self, points: np.ndarray, frequency: float) -> np.ndarray:
        scaled = points * frequency
        base = np.floor(scaled).astype(np.int64)
        frac = scaled - base
        smooth = frac * frac * (3 - 2 * frac)
        out = np.zeros(len(points))
        for corner in np.ndindex(2, 2, 2):
            offset = np.array(corner)
            weight = np.prod(np.where(offset, smooth, 1 - smooth), axis=1)
            out += weight * self._lattice(base + offset)
        return out

    def fractal(self, points: np.ndarray, frequency: float, octaves: int) -> np.ndarray:
        """Sum of octaves, each twice the frequency and half the amplitude; in [0, 1]."""
        total, norm, amplitude = np.zeros(len(points)), 0.0, 1.0
        for octave in range(octaves):
            total += amplitude * self(points + 17.0 * octave, frequency * 2**octave)
            norm += amplitude
            amplitude *= 0.5
        return total / norm


def _band(coordinate: np.ndarray, period: float, width: float) -> np.ndarray:
    """1 inside thin lines of the given width repeating with the given period, else 0 (anti-aliasing is the camera's job)."""
    phase = np.mod(coordinate, period)
    return (phase < width).astype(np.float64)


def body_albedo(canonical: np.ndarray, noise: ValueNoise, palette: np.ndarray) -> np.ndarray:
    """(N, 3) RGB for body points: a horizontally striped top over mottled skin, with fine pin lines.

    `palette` is (4, 3): skin, stripe A, stripe B, pin line.
    """
    y = canonical[:, 1]
    mottle = noise.fractal(canonical, 40.0, 3)[:, None]  # 2.5 cm cells down to 6 mm
    skin = palette[0] * (0.85 + 0.3 * mottle)
    # Stripes follow a slightly wavy height so edges are not axis-aligned in the images.
    wave = y + 0.01 * np.sin(25.0 * canonical[:, 0]) + 0.008 * np.sin(31.0 * canonical[:, 2])
    stripe = np.where((np.mod(wave, 0.05) < 0.025)[:, None], palette[1], palette[2])
    pin = _band(wave + 0.0125, 0.05, 0.004)[:, None]
    top = stripe * (0.9 + 0.2 * noise.fractal(canonical, 160.0, 2)[:, None]) * (1 - pin) + palette[3] * pin
    on_top = ((y > -0.02) & (y < 0.42) & (np.abs(canonical[:, 0]) < 0.3))[:, None]
    return np.where(on_top, top, skin)


def garment_albedo(canonical: np.ndarray, noise: ValueNoise, palette: np.ndarray) -> np.ndarray:
    """(N, 3) RGB for skirt points: a two-colour check in (arc length, drop) with fine lines and weave noise.

    `canonical` is relative to the waist centre of the rest skirt; the pattern's seam runs down the back.
    `palette` is (3, 3): check A, check B, line.
    """
    arc = np.arctan2(canonical[:, 0], canonical[:, 2]) * np.hypot(canonical[:, 0], canonical[:, 2])
    drop = -canonical[:, 1]
    check = (np.floor(arc / 0.06) + np.floor(drop / 0.06)) % 2
    base = np.where(check[:, None] > 0, palette[0], palette[1])
    lines = np.maximum(_band(arc, 0.03, 0.003), _band(drop, 0.03, 0.003))[:, None]
    weave = noise.fractal(canonical, 250.0, 2)[:, None]  # 4 mm threads
    return (base * (0.8 + 0.4 * weave)) * (1 - lines) + palette[2] * lines
