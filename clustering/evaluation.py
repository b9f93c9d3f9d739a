"""Held-out reconstruction: how well a layout's markers predict every dense marker.

Linear model: ridge regression of all markers' positions (3 coordinates each) from the layout
markers' positions, with an intercept — equivalent to regressing displacements from any fixed
neutral pose. Gaps: a test frame is predicted from the layout markers present in it (a model
is fitted per presence pattern on the training frames where those markers are all present); each
target coordinate is fitted on the training frames where that target is present. Layout markers
present in a frame are reproduced exactly (they are measured). Errors are Euclidean distances, mm.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from mocaptk.errors import OptionError
from mocaptk.trajectories import Take

from .baselines import farthest_point_layout, kmeans_layout, random_layout
from .neutral import neutral_pose
from .reconstruction_models import (DEFAULT_RIDGE, FaceModel, ReconstructionModel, RidgeMoments, _by_pattern,
                                    fit_model, fit_reconstruction)


def reconstruct(model: ReconstructionModel | FaceModel, test: np.ndarray) -> np.ndarray:
    """Predicted positions ``(frames, markers, 3)`` mm of ``test`` from its layout markers.

    Frames with no layout marker present are NaN; present layout markers are copied.
    """
    return model.predict_positions(np.asarray(test, dtype=np.float64)[:, model.layout])


def reconstruction_errors(model: ReconstructionModel | FaceModel, test: np.ndarray) -> np.ndarray:
    """Per-point reconstruction error ``(frames, markers)`` mm; NaN where truth or prediction is missing."""
    test = np.asarray(test, dtype=np.float64)
    return point_errors(reconstruct(model, test), test)


def point_errors(pred: np.ndarray, test: np.ndarray) -> np.ndarray:
    """Euclidean distances ``(frames, markers)`` mm of ``pred`` and ``test`` (both (frames, markers, 3)),
    NaN where either is missing or infinite."""
    # np.linalg.norm's own sum, without its copies and np.where's (the same numbers)
    diff = pred - test
    diff *= diff
    err = np.sqrt(np.add.reduce(diff, axis=2))
    err[np.isinf(err)] = np.nan
    return err


def error_summary(errors: np.ndarray, *, regions: Mapping[str, Sequence[int]] | None = None) -> dict:
    """RMSE and 95th-percentile error (mm) over all finite points, and per region.

    Parameters
    ----------
    errors : (frames, markers) float, mm, NaN = not evaluated
    regions : {name: marker indices}, optional
    """
    def stats(values: np.ndarray) -> dict:
        finite = values[np.isfinite(values)]
        if finite.size == 0:
            return {"rmse_mm": float("nan"), "p95_mm": float("nan"), "points": 0}
        return {"rmse_mm": float(np.sqrt(np.mean(finite ** 2))),
                "p95_mm": float(np.percentile(finite, 95)), "points": int(finite.size)}

    out = stats(np.asarray(errors))
    if regions:
        out["regions"] = {name: stats(errors[:, np.asarray(idx, dtype=np.intp)])
                          for name, idx in sorted(regions.items())}
    return out


def holdout_splits(n_frames: int, takes: Sequence[Take] = (), *, split: str = "blocks",
                   folds: int = 5) -> list[tuple[np.ndarray, np.ndarray]]:
    """Train/test frame indices for held-out evaluation.

    ``split="blocks"``: every take (or the whole session without takes) is cut into ``folds``
    contiguous blocks; fold *i* tests on block *i* of every take and trains on the rest.
    ``split="takes"``: leave one take out (needs >= 2 takes).
    """
    segments = [(t.start, t.end) for t in takes] or [(0, n_frames)]
    if split == "takes":
        if len(segments) < 2:
            raise OptionError("--split takes needs a session with at least 2 takes")
        out = []
        for start, end in segments:
            test = np.arange(start, end)
            out.append((np.setdiff1d(np.arange(n_frames), test), test))
        return out
    if split != "blocks":
        raise OptionError(f"unknown split {split!r} (use 'blocks' or 'takes')")
    if folds < 2:
        raise OptionError(f"need at least 2 folds, got {folds}")
    fold_of = np.full(n_frames, -1)
    for start, end in segments:
        edges = np.linspace(start, end, folds + 1).round().astype(int)
        for i in range(folds):
            fold_of[edges[i]:edges[i + 1]] = i
    out = []
    for i in range(folds):
        test = np.flatnonzero(fold_of == i)
        train = np.flatnonzero((fold_of != i) & (fold_of >= 0))
        if test.size and train.size:
            out.append((train, test))
    if not out:
        raise OptionError(f"too few frames ({n_frames}) for {folds} folds")
    return out


def heldout_errors(positions: np.ndarray, layout_idx: Sequence[int] | np.ndarray,
                   splits: Sequence[tuple[np.ndarray, np.ndarray]], *,
                   test: np.ndarray | None = None, ridge: float = DEFAULT_RIDGE,
                   model_kind: str | None = None) -> np.ndarray:
    """Errors ``(frames, markers)`` mm of held-out frames.

    With ``test`` (a separate performance, same markers): fit on all of ``positions``, return the
    errors on ``test``. Otherwise pool the test frames of every split (frames never tested stay NaN).
    ``model_kind``: a kind of :func:`~mocaptk.clustering.reconstruction_models.fit_model`
    (default: ``evaluate``'s exact ridge).
    """
    positions = np.asarray(positions, dtype=np.float64)

    def fit(train: np.ndarray) -> ReconstructionModel | FaceModel:
        if model_kind is None:
            return fit_reconstruction(train, layout_idx, ridge=ridge)
        return fit_model(train, layout_idx, kind=model_kind, ridge=ridge, expected_error=False)

    if test is not None:
        return reconstruction_errors(fit(positions), test)
    errors = np.full(positions.shape[:2], np.nan)
    for train_idx, test_idx in splits:
        model = fit(positions[train_idx])
        errors[test_idx] = reconstruction_errors(model, positions[test_idx])
    return errors


def heldout_errors_of_layouts(positions: np.ndarray, layouts: Sequence[Sequence[int] | np.ndarray],
                              splits: Sequence[tuple[np.ndarray, np.ndarray]], *,
                              test: np.ndarray | None = None, ridge: float = DEFAULT_RIDGE) -> Iterator[np.ndarray]:
    """:func:`heldout_errors` (the exact ridge) of each layout in turn, every training set
    summarised once (:class:`~mocaptk.clustering.reconstruction_models.RidgeMoments`): a layout's
    sub-models cost small solves and a pass over the frames with gaps. Same numbers to rounding
    (~1e-9 mm)."""
    positions = np.asarray(positions, dtype=np.float64)
    if test is not None:
        moments = RidgeMoments.fit(positions, ridge=ridge)
        for layout in layouts:
            yield reconstruction_errors(moments.model(layout), test)
        return
    fits = [(RidgeMoments.fit(positions[train], ridge=ridge), held) for train, held in splits]
    for layout in layouts:
        errors = np.full(positions.shape[:2], np.nan)
        for moments, held in fits:
            errors[held] = reconstruction_errors(moments.model(layout), positions[held])
        yield errors


@dataclass(frozen=True, eq=False)
class GapFreeRidge:
    """:func:`fit_reconstruction` of gap-free training frames for any layout, from one Gram matrix.

    Without gaps every sub-model (one per presence pattern of the test frames) is fitted on all
    training frames, so it needs only blocks of the centred (3M, 3M) Gram matrix: a layout costs
    one small solve per pattern, no pass over the training frames. Same numbers as
    :func:`heldout_errors` to rounding (~1e-12 mm).
    """

    mean: np.ndarray  # (3M,) training mean, mm
    gram: np.ndarray  # (3M, 3M) centred training Gram matrix, mm²
    ridge: float

    @classmethod
    def fit(cls, train: np.ndarray, *, ridge: float = DEFAULT_RIDGE) -> GapFreeRidge:
        """From gap-free training frames ``(frames, markers, 3)`` mm."""
        flat = np.asarray(train, dtype=np.float64).reshape(train.shape[0], -1)
        if not np.isfinite(flat).all():
            raise ValueError("GapFreeRidge needs gap-free training frames")
        mean = flat.mean(axis=0)
        centred = flat - mean
        return cls(mean, centred.T @ centred, float(ridge))

    def errors(self, layout_idx: Sequence[int] | np.ndarray, test: np.ndarray) -> np.ndarray:
        """Per-point errors ``(frames, markers)`` mm of ``test``, as :func:`reconstruction_errors`."""
        test = np.asarray(test, dtype=np.float64)
        n_markers = test.shape[1]
        layout = np.unique(np.asarray(layout_idx, dtype=np.intp))

        def solve(pattern: np.ndarray, x: np.ndarray) -> np.ndarray:
            cols = (3 * layout[pattern][:, None] + np.arange(3)).ravel()
            block = self.gram[np.ix_(cols, cols)]
            lam = self.ridge * max(float(np.trace(block)) / cols.size, 1e-12)
            coef = np.linalg.solve(block + lam * np.eye(cols.size), self.gram[cols])
            return ((x.reshape(len(x), -1) - self.mean[cols]) @ coef + self.mean).reshape(len(x), n_markers, 3)

        return point_errors(_by_pattern(test[:, layout], layout, n_markers, solve), test)


def baseline_layouts(positions: np.ndarray, count: int, *, n_random: int = 10, seed: int = 0,
                     frame_step: int = 1) -> dict[str, list[np.ndarray]]:
    """Baseline layouts of ``count`` markers chosen from a session ``(frames, markers, 3)`` mm.

    ``random``: ``n_random`` seeds (``seed``, ``seed+1``, ...); ``farthest-point`` on the neutral
    pose (per-marker median); ``kmeans`` on displacement trajectories sampled every ``frame_step``.
    """
    positions = np.asarray(positions, dtype=np.float64)
    n_markers = positions.shape[1]
    neutral = neutral_pose(positions)
    disp = positions[::frame_step] - neutral[None]
    return {
        "random": [random_layout(n_markers, count, seed=seed + i) for i in range(n_random)],
        "farthest-point": [farthest_point_layout(neutral, count)],
        "kmeans": [kmeans_layout(disp, count, seed=seed)],
    }


def compare_layouts(positions: np.ndarray, layouts: Mapping[str, Sequence[np.ndarray]],
                    splits: Sequence[tuple[np.ndarray, np.ndarray]], *, test: np.ndarray | None = None,
                    regions: Mapping[str, Sequence[int]] | None = None,
                    ridge: float = DEFAULT_RIDGE) -> dict[str, dict]:
    """Held-out error summary per named layout method.

    ``layouts`` maps a method name to one or more layouts (e.g. random seeds). With several,
    the summary holds the mean over them plus ``rmse_sd_mm`` / ``p95_sd_mm`` (sample sd).
    """
    return _compared(positions, layouts, splits, test=test, regions=regions, ridge=ridge)[0]


def _compared(positions: np.ndarray, layouts: Mapping[str, Sequence[np.ndarray]],
              splits: Sequence[tuple[np.ndarray, np.ndarray]], *, test: np.ndarray | None,
              regions: Mapping[str, Sequence[int]] | None, ridge: float) -> tuple[dict[str, dict], np.ndarray]:
    """:func:`compare_layouts` and the held-out errors (frames, markers) mm of the first layout.

    Every layout is an independent computation, shared among the CPUs (:func:`shared_map`: the
    same bits as one after another); the first one's errors are computed in this process."""
    from mocaptk.background import shared_map

    flat = [idx for group in layouts.values() for idx in group]

    def summarised(item: tuple[int, np.ndarray]) -> tuple[dict, np.ndarray | None]:
        errors = heldout_errors(positions, item[1], splits, test=test, ridge=ridge)
        return error_summary(errors, regions=regions), errors if item[0] == 0 else None

    done = iter(shared_map(summarised, list(enumerate(flat)), what="a held-out evaluation"))
    out: dict[str, dict] = {}
    first = None
    for name, group in layouts.items():
        summaries = []
        for _ in group:
            summary, errors = next(done)
            summaries.append(summary)
            first = errors if first is None else first
        out[name] = _mean_summary(summaries)
        out[name]["count"] = int(np.unique(np.asarray(group[0])).size)
        out[name]["layouts"] = len(group)
    return out, first


def _mean_summary(summaries: list[dict]) -> dict:
    if len(summaries) == 1:
        return summaries[0]
    out: dict = {}
    for key in ("rmse_mm", "p95_mm"):
        values = np.array([s[key] for s in summaries])
        out[key] = float(values.mean())
        out[key.replace("_mm", "_sd_mm")] = float(values.std(ddof=1))
    out["points"] = summaries[0]["points"]
    if "regions" in summaries[0]:
        out["regions"] = {
            name: {key: float(np.mean([s["regions"][name][key] for s in summaries]))
                   for key in ("rmse_mm", "p95_mm")}
            for name in summaries[0]["regions"]}
    return out


@dataclass(frozen=True)
class LayoutEvaluation:
    """:func:`layout_evaluation`'s result: ``result`` as :func:`evaluate_layout`'s, the compared
    ``layouts`` (name → marker indices, the layout under test first) and ``errors`` (frames,
    markers) mm, the layout's held-out errors (NaN: never tested)."""

    result: dict
    layouts: dict[str, list[np.ndarray]]
    errors: np.ndarray


def evaluate_layout(positions: np.ndarray, layout_idx: Sequence[int] | np.ndarray, *,
                    takes: Sequence[Take] = (), test: np.ndarray | None = None,
                    regions: Mapping[str, Sequence[int]] | None = None, name: str = "layout",
                    split: str = "blocks", folds: int = 5, n_random: int = 10, seed: int = 0,
                    ridge: float = DEFAULT_RIDGE) -> dict:
    """A layout against random / farthest-point / k-means layouts of the same size.

    Parameters
    ----------
    positions : (frames, markers, 3) mm
        The session (layouts are chosen from it; the reconstruction is fitted on its training frames).
    layout_idx : marker indices of the layout under test
    takes : the session's takes (held-out splits follow them, see :func:`holdout_splits`)
    test : (frames', markers, 3) mm, optional
        Separate performance: fit on the whole session, test here (no splits).

    Returns
    -------
    dict ``{"count", "protocol", "methods": {name: summary, "random": ..., ...}}``.
    """
    return layout_evaluation(positions, layout_idx, takes=takes, test=test, regions=regions, name=name,
                             split=split, folds=folds, n_random=n_random, seed=seed, ridge=ridge).result


def layout_evaluation(positions: np.ndarray, layout_idx: Sequence[int] | np.ndarray, *,
                      takes: Sequence[Take] = (), test: np.ndarray | None = None,
                      regions: Mapping[str, Sequence[int]] | None = None, name: str = "layout",
                      split: str = "blocks", folds: int = 5, n_random: int = 10, seed: int = 0,
                      ridge: float = DEFAULT_RIDGE) -> LayoutEvaluation:
    """:func:`evaluate_layout` with the layouts it compared and the layout's held-out errors, for
    callers that go on with them (``evaluate``'s lost-marker column and report)."""
    idx = np.unique(np.asarray(layout_idx, dtype=np.intp))
    splits = [] if test is not None else holdout_splits(positions.shape[0], takes, split=split, folds=folds)
    layouts = {name: [idx], **baseline_layouts(positions, idx.size, n_random=n_random, seed=seed)}
    protocol = ({"test": "separate performance", "frames": int(test.shape[0])} if test is not None
                else {"test": f"held-out {split}", "folds": len(splits)})
    protocol.update({"ridge": ridge, "random_seeds": n_random})
    methods, errors = _compared(positions, layouts, splits, test=test, regions=regions, ridge=ridge)
    return LayoutEvaluation({"count": int(idx.size), "protocol": protocol, "methods": methods}, layouts, errors)
