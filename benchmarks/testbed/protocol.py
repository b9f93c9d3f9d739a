"""Expression weights over time: a range-of-motion protocol and a performance process of their own.

Range of motion (:func:`rom_weights`): region blocks in the order jaw → mouth → cheek/nose → eye →
brow (the project's synth goes brow → chin), then a mixed block. Inside a block each shape is
shown single-sided (left, then right, at independent random intensities 0.35–1) and then both
sides at once; unilateral shapes twice at two intensities. Each move: cosine ease in 0.25–0.6 s,
hold 0.3–1.2 s, ease out, rest 0.15–0.5 s. The mixed block pairs random shapes of two regions.

Performance (:func:`performance_weights`): a sum of processes, never a replay of the ROM moves:
coarticulated speech (viseme targets at ~4–6 syllables/s, smoothed by a 35 ms Gaussian), three
emotion latents (Ornstein–Uhlenbeck, rectified) driving co-activations with per-episode left/right
asymmetry, smirks, conjugate gaze with saccades, blinks (Poisson, some winks) and long holds
(2–4 s where every weight but the blinks is frozen).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d

BLOCKS = (
    ("jaw", ("jawOpen", "jawForward", "jawLeft", "jawRight")),
    ("mouth", ("mouthSmile", "mouthFrown", "mouthDimple", "mouthStretch", "mouthPress", "mouthLowerDown",
               "mouthUpperUp", "mouthFunnel", "mouthPucker", "mouthRollLower", "mouthRollUpper",
               "mouthShrugLower", "mouthShrugUpper", "mouthLeft", "mouthRight")),
    ("cheek", ("cheekPuff", "cheekRaiser", "cheekSquint", "noseSneer")),
    ("eye", ("eyeBlink", "eyeSquint", "eyeWide", "eyeLookUp", "eyeLookDown", "eyeLookIn", "eyeLookOut")),
    ("brow", ("browDown", "browInnerUp", "browOuterUp")),
)

#: Visemes: a few shapes each (weights at full articulation).
VISEMES = (
    {"jawOpen": 0.55, "mouthLowerDown_L": 0.3, "mouthLowerDown_R": 0.3},  # aa
    {"jawOpen": 0.2, "mouthStretch_L": 0.45, "mouthStretch_R": 0.4, "mouthSmile_L": 0.15, "mouthSmile_R": 0.15},  # ee
    {"jawOpen": 0.12, "mouthPucker": 0.75, "mouthFunnel": 0.35},  # oo
    {"jawOpen": 0.3, "mouthFunnel": 0.6},  # oh
    {"mouthPress_L": 0.5, "mouthPress_R": 0.5, "mouthRollLower": 0.15, "mouthRollUpper": 0.1},  # m b p
    {"jawOpen": 0.08, "mouthRollLower": 0.5, "mouthUpperUp_L": 0.2, "mouthUpperUp_R": 0.2},  # f v
    {"jawOpen": 0.18, "mouthShrugUpper": 0.2, "mouthStretch_L": 0.2, "mouthStretch_R": 0.2},  # s t d
    {"jawOpen": 0.25, "mouthPucker": 0.3, "mouthFunnel": 0.3, "mouthShrugUpper": 0.15},  # sh ch
)

#: Emotion latents → co-activations (left-side names; ``_R`` twins follow with an asymmetry).
EMOTIONS = (
    {"mouthSmile": 0.8, "cheekSquint": 0.5, "cheekRaiser": 0.45, "eyeSquint": 0.35, "mouthDimple": 0.2},
    {"browDown": 0.7, "browInnerUp": 0.35, "mouthFrown": 0.55, "noseSneer": 0.25, "mouthShrugLower": 0.3},
    {"browInnerUp": 0.7, "browOuterUp": 0.8, "eyeWide": 0.6, "jawOpen": 0.25},
)


def _side_names(stem: str, names: tuple[str, ...]) -> list[str]:
    """``[stem_L, stem_R]`` when the model has them, else ``[stem]``."""
    pair = [f"{stem}_L", f"{stem}_R"]
    return pair if pair[0] in names else [stem]


def _ease(n: int) -> np.ndarray:
    return 0.5 - 0.5 * np.cos(np.linspace(0.0, np.pi, n))


def _move(rng: np.random.Generator, rate: float) -> np.ndarray:
    """One move's envelope 0 → 1 → 0 and its rest, (frames,)."""
    up, hold, down, rest = (int(rate * rng.uniform(*r)) for r in ((0.25, 0.6), (0.3, 1.2), (0.25, 0.6), (0.15, 0.5)))
    return np.concatenate([_ease(max(up, 2)), np.ones(hold), _ease(max(down, 2))[::-1], np.zeros(rest)])


def rom_weights(names: tuple[str, ...], *, rate: float, seed: int) -> tuple[np.ndarray, list[tuple[str, int, int]]]:
    """(frames, E) weights in ``names`` order and takes ``(name, start, end)`` of the ROM session."""
    rng = np.random.default_rng([seed, 31])
    col = {n: i for i, n in enumerate(names)}
    rows: list[np.ndarray] = []
    takes = []
    frame = 0

    def add(weights: dict[str, float]) -> None:
        env = _move(rng, rate)
        block = np.zeros((env.size, len(names)))
        for name, w in weights.items():
            block[:, col[name]] = w * env
        if "mouthClose" in weights:  # mouthClose only exists on an open jaw
            block[:, col["jawOpen"]] = np.maximum(block[:, col["jawOpen"]], block[:, col["mouthClose"]])
        rows.append(block)

    lead = int(rate * 1.0)
    rows.append(np.zeros((lead, len(names))))  # a still start: the neutral
    frame += lead
    for block_name, stems in BLOCKS:
        start = frame
        for stem in stems:
            sides = _side_names(stem, names)
            if len(sides) == 2:
                add({sides[0]: rng.uniform(0.35, 1.0)})
                add({sides[1]: rng.uniform(0.35, 1.0)})
                add({s: rng.uniform(0.5, 1.0) for s in sides})
            else:
                add({stem: rng.uniform(0.35, 0.65)})
                add({stem: rng.uniform(0.7, 1.0)})
        if block_name == "jaw":
            add({"jawOpen": 0.7, "mouthClose": rng.uniform(0.4, 0.7)})
        frame = sum(len(r) for r in rows)
        takes.append((f"rom_{block_name}", start, frame))
    start = frame
    for _ in range(14):  # mixed: two shapes of two regions, random sides and intensities
        a, b = rng.choice(len(BLOCKS), size=2, replace=False)
        picks = {}
        for block in (a, b):
            stem = str(rng.choice(BLOCKS[block][1]))
            sides = _side_names(stem, names)
            for s in (sides if rng.random() < 0.6 else [str(rng.choice(sides))]):
                picks[s] = rng.uniform(0.3, 1.0)
        add(picks)
    frame = sum(len(r) for r in rows)
    takes.append(("rom_mixed", start, frame))
    return np.concatenate(rows), takes


def _ou(rng: np.random.Generator, n: int, rate: float, tau_s: float) -> np.ndarray:
    """Unit-variance Ornstein–Uhlenbeck process (n,) with time constant ``tau_s``."""
    a = np.exp(-1.0 / (rate * tau_s))
    out = np.empty(n)
    out[0] = rng.normal()
    noise = rng.normal(size=n) * np.sqrt(1 - a * a)
    for i in range(1, n):
        out[i] = a * out[i - 1] + noise[i]
    return out


def _piecewise(rng: np.random.Generator, n: int, rate: float, mean_s: tuple[float, float]) -> np.ndarray:
    """Segment boundaries (frame indices) with lengths uniform in ``mean_s`` seconds."""
    edges = [0]
    while edges[-1] < n:
        edges.append(edges[-1] + max(1, int(rate * rng.uniform(*mean_s))))
    return np.minimum(np.array(edges), n)


def performance_weights(names: tuple[str, ...], *, rate: float, seconds: float, seed: int) -> np.ndarray:
    """(frames, E) weights of a performance in ``names`` order, in [0, 1]."""
    rng = np.random.default_rng([seed, 77])
    n = int(rate * seconds)
    col = {nm: i for i, nm in enumerate(names)}
    w = np.zeros((n, len(names)))

    # speech: talking bursts and pauses; syllable targets held, then smoothed (coarticulation)
    speech = np.zeros((n, len(names)))
    talking = np.zeros(n, dtype=bool)
    t = int(rate * rng.uniform(0.3, 1.5))
    while t < n:
        burst = int(rate * rng.uniform(2.0, 6.0))
        talking[t:t + burst] = True
        t += burst + int(rate * rng.uniform(0.5, 2.5))
    edges = _piecewise(rng, n, rate, (0.14, 0.26))
    for a, b in zip(edges[:-1], edges[1:]):
        if not talking[a:b].any():
            continue
        gain = rng.uniform(0.6, 1.25)
        for name, value in VISEMES[int(rng.integers(len(VISEMES)))].items():
            speech[a:b, col[name]] = value * gain * rng.uniform(0.85, 1.15)
    w += gaussian_filter1d(speech, sigma=0.035 * rate, axis=0)

    # emotions: rectified OU latents, co-activations with per-episode asymmetry
    for recipe in EMOTIONS:
        level = np.maximum(_ou(rng, n, rate, rng.uniform(1.0, 2.5)) - 0.4, 0.0) * 0.7
        edges = _piecewise(rng, n, rate, (2.0, 6.0))
        asym = np.ones(n)
        for a, b in zip(edges[:-1], edges[1:]):
            asym[a:b] = rng.uniform(0.55, 1.45)
        asym = gaussian_filter1d(asym, sigma=0.2 * rate)
        for stem, gain in recipe.items():
            sides = _side_names(stem, names)
            if len(sides) == 2:
                w[:, col[sides[0]]] += gain * level * asym
                w[:, col[sides[1]]] += gain * level * (2.0 - asym)
            else:
                w[:, col[stem]] += gain * level

    # smirks: one-sided smile + dimple + the mouth pulled to that side
    for _ in range(int(seconds / 12) + 1):
        start, length = int(rng.integers(0, n)), int(rate * rng.uniform(0.8, 2.5))
        side = str(rng.choice(["L", "R"]))
        env = np.zeros(n)
        seg = _move(rng, rate)[:length]
        env[start:start + seg.size] = seg[: n - start]
        pull = "mouthLeft" if side == "L" else "mouthRight"  # the actor's left
        for name, gain in ((f"mouthSmile_{side}", 0.7), (f"mouthDimple_{side}", 0.4), (pull, 0.35)):
            w[:, col[name]] += gain * env

    # jaw drift: small lateral / forward wander
    for name, gain in (("jawLeft", 0.15), ("jawRight", 0.15), ("jawForward", 0.12)):
        w[:, col[name]] += gain * np.maximum(_ou(rng, n, rate, 1.5), 0.0)

    # gaze: conjugate saccades to random targets (40 ms transitions)
    edges = _piecewise(rng, n, rate, (0.4, 2.0))
    yaw, pitch = np.zeros(n), np.zeros(n)
    for a, b in zip(edges[:-1], edges[1:]):
        yaw[a:b], pitch[a:b] = rng.uniform(-0.8, 0.8), rng.uniform(-0.6, 0.6)
    yaw, pitch = gaussian_filter1d(yaw, 0.02 * rate), gaussian_filter1d(pitch, 0.02 * rate)
    left, right = np.maximum(yaw, 0), np.maximum(-yaw, 0)  # looking to the actor's left / right
    w[:, col["eyeLookOut_L"]] += left
    w[:, col["eyeLookIn_R"]] += left
    w[:, col["eyeLookIn_L"]] += right
    w[:, col["eyeLookOut_R"]] += right
    for side in ("L", "R"):
        w[:, col[f"eyeLookUp_{side}"]] += np.maximum(pitch, 0)
        w[:, col[f"eyeLookDown_{side}"]] += np.maximum(-pitch, 0)

    # long holds: everything frozen (blinks come after)
    for _ in range(int(seconds / 20) + 1):
        start, length = int(rng.integers(0, max(1, n - 1))), int(rate * rng.uniform(2.0, 4.0))
        stop = min(n, start + length)
        w[start:stop] = w[start]

    # blinks: Poisson, fast close, slower open; one in ten a wink
    t = 0.0
    while True:
        t += rng.exponential(3.2)
        start = int(t * rate)
        if start >= n:
            break
        close, open_ = max(2, int(0.06 * rate)), max(3, int(rng.uniform(0.1, 0.18) * rate))
        env = np.concatenate([_ease(close), _ease(open_)[::-1]]) * rng.uniform(0.8, 1.0)
        stop = min(n, start + env.size)
        sides = ["L", "R"] if rng.random() > 0.1 else [str(rng.choice(["L", "R"]))]
        for side in sides:
            c = col[f"eyeBlink_{side}"]
            w[start:stop, c] = np.maximum(w[start:stop, c], env[: stop - start])
    return np.clip(w, 0.0, 1.0)
