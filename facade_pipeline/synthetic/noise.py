"""Deterministic randomness: named random streams and procedural value noise.

Every consumer draws from its own stream, keyed by the scene seed and a name (and an index), so that
switching one effect off never shifts the random numbers another effect sees.
"""

from __future__ import annotations

import zlib

import numpy as np

_M1 = np.uint32(0x7FEB352D)
_M2 = np.uint32(0x846CA68B)


def rng_for(seed: int, name: str, index: int = 0) -> np.random.Generator:
    """An independent generator for (seed, stream name, index)."""
    return np.random.default_rng(
        np.random.SeedSequence([seed & 0xFFFFFFFF, zlib.crc32(name.encode()), index])
    )


def _hash_u32(x: np.ndarray) -> np.ndarray:
    """A 32-bit integer mixing function (xorshift-multiply), elementwise on uint32."""
    x = x.astype(np.uint32, copy=True)
    x ^= x >> np.uint32(16)
    x *= _M1
    x ^= x >> np.uint32(15)
    x *= _M2
    x ^= x >> np.uint32(16)
    return x


def lattice_random(i: np.ndarray, j: np.ndarray, seed: int) -> np.ndarray:
    """A uniform value in [0, 1) for each integer lattice point (i, j) and seed."""
    with np.errstate(over="ignore"):
        h = _hash_u32(
            np.asarray(i).astype(np.int64).astype(np.uint32) * np.uint32(0x9E3779B1)
            ^ _hash_u32(np.asarray(j).astype(np.int64).astype(np.uint32) + np.uint32(seed & 0xFFFFFFFF))
        )
    return h.astype(np.float64) / 4294967296.0


def value_noise(u: np.ndarray, v: np.ndarray, seed: int) -> np.ndarray:
    """Smooth value noise in [0, 1) at continuous coordinates (u, v) in lattice units: random values on
    the integer lattice, interpolated with a C1 smoothstep."""
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    i0, j0 = np.floor(u), np.floor(v)
    fu, fv = u - i0, v - j0
    su, sv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
    a = lattice_random(i0, j0, seed)
    b = lattice_random(i0 + 1, j0, seed)
    c = lattice_random(i0, j0 + 1, seed)
    d = lattice_random(i0 + 1, j0 + 1, seed)
    return (a * (1 - su) + b * su) * (1 - sv) + (c * (1 - su) + d * su) * sv


def fbm(u: np.ndarray, v: np.ndarray, seed: int, octaves: int = 3) -> np.ndarray:
    """Fractal sum of ``octaves`` value-noise octaves (frequency x2, amplitude /2 each), in [0, 1)."""
    total = np.zeros(np.broadcast(u, v).shape)
    amp, norm, freq = 1.0, 0.0, 1.0
    for k in range(octaves):
        total += amp * value_noise(np.asarray(u) * freq, np.asarray(v) * freq, seed + 7919 * k)
        norm += amp
        amp *= 0.5
        freq *= 2.0
    return total / norm
