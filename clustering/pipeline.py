"""Session → layout: the single place where a layout is computed from a dense session.

Steps: drop unusable (all-NaN) markers → stabilize (rigid head motion removed) → neutral pose →
regions → takes per region → per region: sampled positions, consolidated correlation, threshold
clustering + reassignment → sides, sagittal plane, mirroring → :class:`Layout`.
Nothing here prints or writes files; problems the user should know about are returned as
``notes`` (the CLI prints them as warnings).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mocaptk.acquisition.orientation import labels_warning
from mocaptk.errors import InputFileError, MocaptkError, OptionError, source_error
from mocaptk.trajectories import Take, Trajectories

from .correlation import consolidated_correlation
from .cluster_result import ClusterResult, RegionMatrix
from .layout import Cluster, Layout, RegionResult
from .neutral import max_displacement, neutral_pose, seen_markers
from .regions import default_regions, unassigned
from .symmetry import face_sides, is_half_capture, mirror_clusters, plane_frame
from .takes import all_frames, region_segments, sample_frames
from .threshold import RegionClusters, cluster_region, keep_representatives, region_statistics

#: Fewer sampled frames than this in a region make correlations meaningless.
MIN_SAMPLES = 3


#: Layout method of ``mocaptk cluster``: the best measured on held-out data (docs/layout-methods.md).
#: The paper's rule still sets the count (``factor``) and the influence regions.
DEFAULT_METHOD = "hybrid"


@dataclass(frozen=True)
class ClusterOptions:
    """Options of :func:`cluster_session` (CLI flags of ``mocaptk cluster``).

    ``regions``: ``{name: labels}`` (None: default regions); ``takes``: None = the session's
    takes; ``mirror``: None = mirror when the labels show a half face + midline. ``method``: the
    layout method choosing the measured markers (``"paper"``: the paper's representatives);
    ``markers``: their number (None: the paper's rule at ``factor``; with ``"paper"`` the factor
    is then found by bisection). ``rig``: ``cara``, ``room`` or a rig file; the method then weighs
    how the rig sees each marker (:func:`~mocaptk.clustering.methods.problem.camera_aware`).
    ``shapes``: (labels, (K, M, 3) mm) a character rig's K shapes at the session's markers
    ``labels`` (``--character``, mapped by the caller): ``set-cover`` covers them instead of the
    session's extreme frames; ``shapes_source`` names them in the layout's parameters.
    ``fill_gaps``: fill every gap from the session's main motion patterns (low-rank) once the head
    motion is removed, so that the patterns are the face's, not the head's.
    """

    factor: float = 1.1
    method: str = DEFAULT_METHOD
    markers: int | None = None  # measured markers of the layout (None: as many as the paper's rule gives)
    step: int = 5
    stabilize: bool = True
    mirror: bool | None = None
    regions: dict[str, list[str]] | None = None
    takes: list[Take] | None = None
    rigid: tuple[str, ...] | None = None  # rigid head markers for stabilization (None: detected)
    rig: str | None = None  # camera rig whose per-marker costs the layout method weighs (None: camera-blind)
    shapes: tuple[tuple[str, ...], np.ndarray] | None = None
    shapes_source: str | None = None
    fill_gaps: bool = False


#: A session whose automatically chosen rigid markers already stay this close (RMS, mm) to their
#: reference positions is head-relative (a head-mounted rig, or cleaned data): fitting a head pose
#: to it would only turn the rigid set's own skin motion into a spurious head motion.
HEAD_RELATIVE_RMS_MM = 1.0
RIGID_WITHOUT_STABILIZING = "--rigid names the markers to stabilize on; it cannot go with --no-stabilize"


def stabilize(traj: Trajectories, *, rigid: Sequence[str] | None = None,
              reference: np.ndarray | None = None) -> tuple[Trajectories, dict[str, Any]]:
    """Remove rigid head motion (acquisition stage); returns the session and a report.

    ``rigid``: labels of the rigid head markers (default: detected automatically). A session that
    is already head-relative (its rigid set moves less than :data:`HEAD_RELATIVE_RMS_MM`) is
    returned unchanged; the report says so. ``reference`` (K, 3) mm: the ``rigid`` markers in the
    head frame to land in (:func:`rigid_reference` of the training session), so that a test or
    production capture is expressed in that session's frame (left unchanged when its rigid set
    is already within :data:`HEAD_RELATIVE_RMS_MM` RMS of it).
    """
    try:
        from mocaptk.acquisition.stabilize import head_relative_markers, stabilize_head
    except ImportError:
        raise OptionError("head stabilization is not available in this installation; "
                          "use --no-stabilize for already head-relative data") from None
    still = None if rigid is not None else head_relative_markers(traj, tolerance_mm=HEAD_RELATIVE_RMS_MM)
    if still is not None:  # recognised before the rigid search and the full-length fit
        return traj, {"rigid_labels": list(still[0]), "applied": False,
                      "rigid_set_motion_rms_mm": still[1], "rms_residual_mm": None}
    result = stabilize_head(traj, rigid_labels=rigid, reference=reference)
    residual = np.asarray(result.rms_residual_mm, dtype=np.float64)
    residual = residual[np.isfinite(residual)]
    rigid = traj.positions[:, traj.index(result.rigid_labels)]
    start = rigid[result.reference_frame] if reference is None else np.asarray(reference, float)
    offsets = np.linalg.norm(rigid - start, axis=2)
    rigid_motion = float(np.sqrt(np.nanmean(offsets ** 2))) if np.isfinite(offsets).any() else 0.0
    applied = rigid_motion >= HEAD_RELATIVE_RMS_MM
    report = {"rigid_labels": list(result.rigid_labels), "applied": applied,
              "rigid_set_motion_rms_mm": rigid_motion,
              "rms_residual_mm": float(residual.mean()) if residual.size else None}
    return (result.trajectories if applied else traj), report


def stabilization_markers(traj: Trajectories) -> tuple[str, ...]:
    """The session's rigid head markers (detected as stabilization detects them), or none when
    no 3 markers move as one body (a session of few markers, all on moving skin)."""
    from mocaptk.acquisition.stabilize import detect_rigid_markers

    try:
        return detect_rigid_markers(traj)
    except MocaptkError:
        return ()


def rigid_reference(session: Trajectories, rigid: Sequence[str]) -> np.ndarray:
    """The ``rigid`` markers' neutral positions (K, 3) mm in ``session`` (stabilized or already
    head-relative): the head frame a test or production capture is stabilized into."""
    from .neutral import neutral_pose

    return neutral_pose(session.positions[:, session.index(list(rigid))])


def check_layout_options(*, method: str, markers: int | None, rig: str | None = None,
                         shapes: bool = False) -> None:
    """Reject an unknown layout method, a marker count < 1, ``--rig`` with the paper's
    representatives or naming no preset and no rig file, and given ``shapes`` (``--character``)
    with a method other than set cover (OptionError / InputFileError)."""
    from .methods import method_names
    if method not in method_names():
        raise OptionError(f"unknown --method {method!r} (choose from {', '.join(method_names())})")
    if shapes and method != "set-cover":
        raise OptionError(f"--character needs --method set-cover (its shapes are what set cover covers), "
                          f"not {method}")
    if markers is not None and markers < 1:
        raise OptionError(f"--markers must be >= 1, got {markers}")
    if rig is not None:
        check_rig(rig, methods=[method])


def check_rig(rig: str, *, methods: Sequence[str]) -> None:
    """Reject ``--rig`` with the paper's representatives (they take no costs) or naming neither a
    preset nor a readable rig file."""
    from mocaptk.acquisition.cameras import RIG_PRESETS
    if "paper" in methods:
        raise OptionError("--rig needs a layout method that weighs camera costs; the paper's "
                          "representatives do not (use another --method)")
    if rig not in RIG_PRESETS:
        from .camera_cost import read_rig_file
        read_rig_file(rig)


def check_options(options: ClusterOptions, n_frames: int, *, source: str | None = None) -> None:
    """Reject a factor <= 0 and a step outside 1..frames-1 (OptionError; naming the session file
    ``source`` when the step does not fit its frames)."""
    if not options.factor > 0:
        raise OptionError(f"--factor must be > 0, got {options.factor}")
    if options.step < 1:
        raise OptionError(f"--step must be >= 1, got {options.step}")
    if options.rigid is not None and not options.stabilize:
        raise OptionError(RIGID_WITHOUT_STABILIZING)
    check_layout_options(method=options.method, markers=options.markers, rig=options.rig)
    if options.step >= n_frames:
        raise source_error(source, f"--step {options.step} is not smaller than the session's {n_frames} frames")


def head_frame(traj: Trajectories, *, options: ClusterOptions) -> tuple[Trajectories, dict[str, Any]]:
    """The session in its head frame (unless ``options.stabilize`` is off) with the stabilization
    report (its rigid set and their reference shape), then gap-filled if ``options.fill_gaps``:
    filled after the head motion is removed, the low-rank basis is spent on the face alone."""
    if options.stabilize:
        traj, stabilization = stabilize(traj, rigid=options.rigid)  # not applied: see stabilization_note
    else:  # recorded all the same: a production capture is posed from them
        stabilization = {"rigid_labels": list(stabilization_markers(traj)), "applied": False,
                         "rigid_set_motion_rms_mm": None, "rms_residual_mm": None}
    if stabilization["rigid_labels"]:
        stabilization["reference"] = rigid_reference(traj, stabilization["rigid_labels"])
    if options.fill_gaps:
        from mocaptk.acquisition.gapfill import fill_low_rank
        traj = traj.replace(positions=fill_low_rank(traj.positions), residuals=None)
    return traj, stabilization


def cluster_session(traj: Trajectories, *, options: ClusterOptions = ClusterOptions(),
                    source: dict[str, Any] | None = None,
                    progress: Callable[[str], None] | None = None,
                    neutral: np.ndarray | None = None) -> ClusterResult:
    """Compute the layout of a dense session.

    Parameters
    ----------
    traj : Trajectories
        Dense session, mm.
    options : ClusterOptions
    source : dict
        ``path``/``sha256`` of the input file, stored in the layout's ``source``.
    progress : callable, optional
        Called with a short description as each region is processed.
    neutral : (markers, 3) float, optional
        :func:`neutral_pose` of ``traj`` as given, mm, when the caller has it (the face check's):
        one median pass over the frames less unless the head motion is removed.
    """
    file = traj.metadata.get("source")  # errors about the session's data name it
    check_options(options, traj.n_frames, source=file)
    notes: list[str] = []
    # unusable markers: never seen
    seen = seen_markers(traj.positions)
    excluded = [label for label, ok in zip(traj.labels, seen) if not ok]
    if excluded:
        notes.append(f"{len(excluded)} markers have no data at all and are left out: "
                     + ", ".join(excluded[:8]) + (" ..." if len(excluded) > 8 else ""))
        traj = traj.select([label for label, ok in zip(traj.labels, seen) if ok])
        neutral = None if neutral is None else np.asarray(neutral)[seen]
    if traj.n_markers < 2:
        raise source_error(file, f"need at least 2 markers with data, the session has {traj.n_markers}")
    if progress:
        progress("stabilizing" if options.stabilize else "choosing the stabilization markers")
    traj, stabilization = head_frame(traj, options=options)
    labels = list(traj.labels)
    if neutral is None or stabilization.get("applied") or options.fill_gaps:
        neutral = neutral_pose(traj.positions)
    displacement = max_displacement(traj.positions, neutral)
    mirror = is_half_capture(labels) if options.mirror is None else options.mirror
    # up, forward and the actor's left from the face itself; the labels' sides only if they agree
    face = face_sides(labels, traj.positions, neutral, half=mirror, displacement=displacement)
    orientation, plane, sides = face.orientation, face.plane, dict(zip(labels, face.sides))
    warning = labels_warning(orientation)
    if warning:
        notes.append(warning)

    if options.regions is not None:
        regions = {name: [m for m in members if m not in excluded]
                   for name, members in options.regions.items()}
        region_method = "regions file"
    else:
        regions, region_method = default_regions(labels, neutral, displacement, frame=orientation.frame)
    loose = unassigned(regions, labels)
    if loose:
        notes.append(f"{len(loose)} markers are in no region and are not clustered: "
                     + ", ".join(loose[:8]) + (" ..." if len(loose) > 8 else ""))

    takes = options.takes if options.takes is not None else traj.takes
    region_names = [name for name, members in regions.items() if members]
    for name in regions:
        if name not in region_names:
            notes.append(f"region {name!r} has no markers with data; skipped")
    segments = region_segments(takes, region_names, traj.n_frames)

    frame = plane_frame(plane, orientation.frame)

    index = {label: i for i, label in enumerate(labels)}
    region_data = []  # per region: (name, point indices, sampled frames, displacement, correlation, notes)
    static_markers: list[str] = []
    for name in region_names:
        if progress:
            progress(f"clustering {name}")
        idx = np.array([index[m] for m in regions[name]], dtype=np.intp)
        frames = sample_frames(segments[name], options.step)
        if frames.size < MIN_SAMPLES:
            raise source_error(file, f"region {name!r}: only {frames.size} frames sampled with --step "
                                     f"{options.step}; use a smaller step")
        whole = segments[name] == [(0, traj.n_frames)]  # the session's own displacement: no copy
        region_disp = displacement[idx] if whole else max_displacement(
            traj.positions[np.ix_(all_frames(segments[name]), idx)], neutral[idx])
        # the region's markers at the sampled frames in one gather (not all markers' frames first)
        corr = consolidated_correlation(traj.positions[np.ix_(frames, idx)])
        static = [regions[name][i] for i in np.flatnonzero(corr.static)]
        static_markers.extend(static)
        region_notes = []
        if static:
            region_notes.append(f"region {name!r}: {len(static)} markers do not move (correlation 0): "
                                + ", ".join(static[:8]) + (" ..." if len(static) > 8 else ""))
        if idx.size < 2:
            region_notes.append(f"region {name!r} has only 1 marker; it is its own representative")
        region_data.append((name, idx, frames, region_disp, corr, region_notes))

    factor = options.factor
    region_clusters = [cluster_region(d[4].matrix, d[3], factor=factor) for d in region_data]
    if options.markers is not None and options.method == "paper":
        factor, region_clusters = _clusters_of_count(
            [(d[4].matrix, d[3]) for d in region_data], options.markers)
    region_results, clusters, matrices = [], [], {}
    for (name, idx, frames, region_disp, corr, region_notes), result in zip(region_data, region_clusters):
        notes.extend(region_notes)
        if idx.size >= 2 and result.mean_correlation <= 0:
            notes.append(f"region {name!r}: mean correlation {result.mean_correlation:.3f} <= 0, so the "
                         "factor's meaning flips (a larger factor gives fewer markers)")
        elif idx.size >= 2 and result.unreachable:
            notes.append(f"region {name!r}: threshold {result.threshold:.3f} (factor {factor:g} x mean "
                         f"correlation {result.mean_correlation:.3f}) is not below its largest correlation "
                         f"{result.max_correlation:.3f}, so the paper's rule makes each of its {idx.size} markers "
                         f"its own cluster (counted in the layout's size{'' if options.method == 'paper' else f'; --method {options.method} places the measured markers, see the table'}); "
                         f"--factor {result.clustering_factor():.3f} or lower clusters it")
        member_labels = regions[name]
        reps = [member_labels[r] for r in result.representatives]
        for k, rep in enumerate(result.representatives):
            members = np.flatnonzero(result.assignment == k)
            members = np.concatenate([[rep], members[members != rep]])
            clusters.append(Cluster(
                representative=member_labels[rep], region=name,
                members=tuple(member_labels[j] for j in members),
                member_correlation={member_labels[j]: float(result.member_correlation[j]) for j in members},
                position=tuple(float(x) for x in neutral[idx[rep]]), side=sides[member_labels[rep]]))
        region_results.append(RegionResult(name, tuple(member_labels), result.mean_correlation,
                                           result.threshold, int(frames.size), tuple(reps)))
        matrices[name] = RegionMatrix(list(member_labels), corr.matrix, result.assignment)

    mirrored: list[Cluster] = []
    if mirror:
        midline = {label for label, side in sides.items() if side == "C"}
        mirrored = mirror_clusters(clusters, plane, labels, midline)
    stabilized = bool(options.stabilize and stabilization.get("applied"))
    parameters = {"factor": factor, "step": options.step, "stabilized": stabilized,
                  "mirror": mirror, "method": "paper", "regions_from": region_method,
                  "takes": [t.as_dict() for t in takes]}
    if options.markers is not None:
        parameters["markers"] = options.markers
    extra = {"stabilization": stabilization, "excluded_markers": excluded, "unassigned_markers": loose,
             "static_markers": static_markers, "notes": notes,
             "sagittal_plane": {"point": plane.point, "normal": plane.normal},
             "orientation": orientation.as_dict()}
    src = {"frames": traj.n_frames, "rate": traj.rate, "markers": traj.n_markers, **(source or {})}
    layout = Layout(src, parameters, tuple(region_results), tuple(clusters + mirrored), extra)
    result = ClusterResult(layout, traj, neutral, matrices, frame, notes)
    if options.method == "paper":
        return result
    from .methods.session_layout import relayout  # the methods build on this module
    if progress:
        progress(f"choosing the layout ({options.method})")
    return relayout(result, method=options.method, count=options.markers, rig=options.rig,
                    shapes=options.shapes, shapes_source=options.shapes_source)


def _clusters_of_count(regions: Sequence[tuple[np.ndarray, np.ndarray]], count: int
                       ) -> tuple[float, list[RegionClusters]]:
    """The paper's clusters with exactly ``count`` representatives over all regions.

    ``regions``: (correlation matrix, displacement) per region. The factor is found by bisection
    (the count grows with it, stepwise); when no factor gives ``count`` exactly, the smallest
    clustering above it drops the representatives created last (per region in creation order,
    the least-moving first), their members joining the kept representative they correlate with
    most. Returns (factor, clusters per region).
    """
    if count < len(regions):
        raise OptionError(f"--markers {count} is fewer than the {len(regions)} regions; the paper's "
                          "rule keeps at least one marker per region")

    statistics = [region_statistics(matrix) for matrix, _ in regions]  # the same at every factor

    def at(factor: float) -> list[RegionClusters]:
        return [cluster_region(matrix, disp, factor=factor, statistics=stats)
                for (matrix, disp), stats in zip(regions, statistics)]

    def total(result: list[RegionClusters]) -> int:
        return sum(r.representatives.size for r in result)

    lo, hi = 1e-3, 1.0
    result_hi = at(hi)
    while total(result_hi) < count and hi < 64:
        lo, hi = hi, hi * 2.0
        result_hi = at(hi)
    for _ in range(40):
        if total(result_hi) == count or hi - lo < 1e-6:
            break
        mid = 0.5 * (lo + hi)
        result = at(mid)
        if total(result) >= count:
            hi, result_hi = mid, result
        else:
            lo = mid
    if total(result_hi) < count:
        raise OptionError(f"the paper's correlation rule cannot give {count} markers here (at most "
                          f"{total(result_hi)}); choose another --method or fewer --markers")
    order = sorted((k, -float(disp[rep]), r) for r, ((_, disp), clusters) in enumerate(zip(regions, result_hi))
                   for k, rep in enumerate(clusters.representatives))
    kept = np.bincount([r for _, _, r in order[:count]], minlength=len(regions))
    return hi, [keep_representatives(matrix, clusters, int(n))
                for (matrix, _), clusters, n in zip(regions, result_hi, kept)]


def load_session(path: str, *, rate: float | None = None, units: str | None = None,
                 layout_folder: Path | None = None) -> tuple[Trajectories, dict[str, Any]]:
    """Read a session file (any format ``read_trajectories`` knows) and describe it for ``source``.

    Returns the trajectories (``Subject:`` prefixes stripped) and ``{"path", "sha256"}`` (the
    file's name and hash); with ``layout_folder`` (where layout.json goes) also ``absolute`` and
    ``relative`` (to that folder), so ``solve`` finds the session from the layout alone.
    """
    from mocaptk.acquisition.formats import read_trajectories

    file = Path(path)
    if file.is_dir():
        raise InputFileError(file, "is a folder, expected a file")
    if not file.is_file():
        raise InputFileError(file, "no such file")
    # the sha256 recorded is that of the bytes read: hashed before, and the file unchanged after
    before = _identity(file)
    with open(file, "rb") as handle:  # streamed: no copy of the whole file in memory
        digest = hashlib.file_digest(handle, "sha256").hexdigest()
    traj = read_trajectories(file, strip_prefixes=True, rate=rate, units=units)
    if _identity(file) != before:
        raise InputFileError(file, "changed while it was read (still being written or copied?); "
                                   "run again when it is complete")
    where = {} if layout_folder is None else {
        "absolute": str(file.resolve()), "relative": os.path.relpath(file.resolve(), Path(layout_folder).resolve())}
    return traj, {"path": file.name, "sha256": digest, **where}


def _identity(file: Path) -> tuple[int, ...]:
    """What changes when a file is rewritten, cut or replaced: inode, size, modification time (ns)."""
    try:
        stat = file.stat()
    except OSError:  # removed meanwhile
        return ()
    return stat.st_ino, stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns


def stabilization_note(stabilization: dict[str, Any]) -> str | None:
    """The note for a session found already head-relative (the normal case with head-mounted cameras);
    None when it was stabilized or stabilization was not asked for."""
    if not stabilization or stabilization.get("applied") or stabilization.get("rigid_set_motion_rms_mm") is None:
        return None  # stabilized, or not asked for (the rigid set is then only recorded)
    return (f"the session is already head-relative (the rigid set {', '.join(stabilization['rigid_labels'])} "
            f"moves {stabilization['rigid_set_motion_rms_mm']:.2f} mm RMS < {HEAD_RELATIVE_RMS_MM} mm): "
            "not stabilized")


def load_session_and_test(session: str | Path, test: str | Path | None, *, stabilized: bool,
                          rate: float | None = None, units: str | None = None,
                          rigid: Sequence[str] | None = None,
                          test_reading: tuple[float | None, str | None] | None = None,
                          ) -> tuple[Trajectories, Trajectories | None, dict[str, Any]]:
    """A session and an optional held-out test file, prepared alike: the session stabilized when
    ``stabilized`` (on ``rigid``, or a detected set), the test taken into the session's head frame
    on that rigid set (``rigid`` alone when the session is not stabilized: it is head-relative).

    ``test_reading``: ``(rate, units)`` for the test file (default: the session's ``rate``, ``units``).
    Returns ``(session, test or None, source)``; a test file lacking session markers raises
    :class:`InputFileError`.
    """
    traj, source = load_session(str(session), rate=rate, units=units)
    if stabilized:
        traj, report = stabilize(traj, rigid=rigid)
        rigid = report["rigid_labels"]
    if test is None:
        return traj, None, source
    test_rate, test_units = (rate, units) if test_reading is None else test_reading
    perf, _ = load_session(str(test), rate=test_rate, units=test_units)
    present = set(perf.labels)
    missing = [label for label in traj.labels if label not in present]
    if missing:
        raise InputFileError(test, f"lacks {len(missing)} markers of the session: {', '.join(missing[:5])}")
    perf = perf.select(traj.labels)
    if rigid:  # into the session's head frame (whether or not the session itself needed stabilizing)
        perf, _ = stabilize(perf, rigid=rigid, reference=rigid_reference(traj, rigid))
    return traj, perf, source
