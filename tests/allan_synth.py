"""Fast synthetic rate noise for Allan tests and benchmarks/allan.py (one definition for both)."""
from __future__ import annotations

import math

import numpy as np
from scipy.signal import lfilter


def synth_rate(n: int, fs: float, n_arw: float, b: float, k: float, seed: int) -> np.ndarray:
    """White (N, u sqrt(s)) + flicker (B, u; octave-spaced Gauss-Markov bank) + random-walk
    (K, u/sqrt(s)) rate noise. Flicker PSD B^2/(2 pi f): each process has variance
    B^2 ln2 / pi (octave spacing)."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / fs
    y = rng.standard_normal(n) * (n_arw / math.sqrt(dt))
    if b > 0:
        q = b * b * math.log(2.0) / math.pi
        tc = 0.5
        while tc <= 4 * n * dt:
            rep = max(1, int(round(tc / 16.0 / dt)))
            phi = math.exp(-rep * dt / tc)
            w = rng.standard_normal(-(-n // rep)) * math.sqrt(q * (1 - phi * phi))
            g = lfilter([1.0], [1.0, -phi], w, zi=[rng.standard_normal() * math.sqrt(q) * phi])[0]
            y += np.repeat(g, rep)[:n]
            tc *= 2.0
    if k > 0:
        y += np.cumsum(rng.standard_normal(n)) * (k * math.sqrt(dt))
    return y
