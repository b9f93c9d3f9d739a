"""``mocaptk cluster``: dense session → optimized marker layout (layout.json + pictures + summary).

Extension points for later issues:
- the layout is computed in ONE place, :func:`mocaptk.clustering.pipeline.cluster_session`
  (``--method`` selects the layout rule there; ``hybrid`` is the default, ``paper`` the paper's);
- every output file is written in ONE place, :func:`write_cluster_outputs` below (rig/guide
  exports add their files there, into the same staging folder, so the whole folder stays atomic).
"""

from __future__ import annotations

from pathlib import Path

import typer

from mocaptk.atomic import claim_output, staged_folder
from mocaptk.errors import shorten, warn

from .app import app
from .options import Quiet, Rate, Rigid, Units, rigid_labels, session_reading
from .report import write_cluster_report


#: Added to a cannot-write message about an output placed next to the input by default.
OUT_HINT = "; use --out to write elsewhere"


def default_out_dir(session: Path) -> Path:
    """``<session stem>_layout/`` next to the session."""
    return session.with_name(f"{session.stem}_layout")


def warn_unless_face(traj, session: Path, *, regions_given: bool, neutral=None) -> None:
    """Refuse a session that is no face capture (a warning only with ``--regions``); warn when its
    size says the units are wrong (see clustering/sanity.py; ``neutral``: the session's neutral
    pose, if known)."""
    from mocaptk.clustering.sanity import check_session
    from mocaptk.errors import InputFileError

    check = check_session(traj, neutral=neutral)
    if check.not_a_face:
        problem = (f"not a face capture: {check.not_a_face}; cluster lays out facial markers (regions, "
                   "sides and guide assume a face): give a facial session, or --regions FILE to cluster "
                   "these markers anyway")
        if not regions_given:
            raise InputFileError(session, problem)
        warn(f"{session}: {problem}")
    if check.units_warning:
        warn(f"{session}: {check.units_warning}")


def _followed_elsewhere(layout) -> list[str]:
    """A line per region with markers but no layout marker of its own: which layout markers its
    markers follow (their influence regions reach into it)."""
    lines = []
    for region in layout.regions:
        if not region.markers or any(c.region == region.name for c in layout.clusters):
            continue
        inside = set(region.markers)
        followed = [f"{c.representative} ({c.region})" for c in layout.clusters if inside & set(c.members)]
        lines.append(f"{region.name}: no layout marker of its own; its {len(inside)} marker"
                     f"{'' if len(inside) == 1 else 's'} follow " + (", ".join(followed) or "no layout marker"))
    return lines


def summary_text(result) -> str:
    """Short text summary: markers per region (measured + mirrored = total), notes, warnings.

    The paper's mean correlation and threshold columns appear when the paper's rule chose the
    markers; with another method they only set the count, which the header says.
    """
    from mocaptk.clustering.pipeline import stabilization_note

    layout = result.layout
    params = layout.parameters
    method = params.get("method", "paper")
    lines = [f"mocaptk cluster: {layout.source.get('path')}  method {method}  factor {params['factor']:g}  "
             f"step {params['step']}  stabilized {params['stabilized']}  mirror {params['mirror']}",
             f"regions from: {params['regions_from']}"]
    actors = layout.source.get("actors")
    if actors:  # one layout for several actors (clustering/multi_actor.py)
        lines.append("actors (evidence pooled): " + ", ".join(
            f"{a['actor']} by {a['by']} (scale {a['scale']:.3f}, residual {a['residual_mm']:.2f} mm)"
            for a in actors))
    if method != "paper":
        count = (f"--markers {params['markers']}" if "markers" in params
                 else f"the paper's rule at factor {params['factor']:g}")
        winner = f" (hybrid contender: {params['winner']}" if "winner" in params else ""
        swaps = params.get("region_cover", [])
        winner += (f", {len(swaps)} region-cover swap{'s' * (len(swaps) > 1)})" if swaps else ")") if winner else ""
        rig = f" for the {params['rig']} rig" if "rig" in params else ""
        lines.append(f"measured markers chosen by {method}{winner}{rig}; count from {count}; "
                     "influence regions by the paper's correlations")
    paper = method == "paper"
    lines += ["", f"{'region':<16}{'dense':>7}{'measured':>10}{'mirrored':>10}{'total':>7}"
              + (f"{'mean C':>9}{'threshold':>11}" if paper else "")]
    sums = [0, 0, 0]
    for region in layout.regions:
        own = sum(c.region == region.name and c.mirrored_from is None for c in layout.clusters)
        mirrored = sum(c.region == region.name and c.mirrored_from is not None for c in layout.clusters)
        sums = [sums[0] + len(region.markers), sums[1] + own, sums[2] + mirrored]
        lines.append(f"{region.name:<16}{len(region.markers):>7}{own:>10}{mirrored:>10}{own + mirrored:>7}"
                     + (f"{region.mean_correlation:>9.3f}{region.threshold:>11.3f}" if paper else ""))
    lines.append(f"{'total':<16}{sums[0]:>7}{sums[1]:>10}{sums[2]:>10}{sums[1] + sums[2]:>7}")
    lines += _followed_elsewhere(layout)
    stabilization = layout.extra.get("stabilization", {})
    rigid = stabilization.get("rigid_labels")
    if rigid and stabilization.get("applied"):
        lines.append(f"stabilized on rigid set: {', '.join(rigid)}")
    note = stabilization_note(stabilization)
    if note:
        lines.append(f"note: {note}")
    for note in result.notes:
        lines.append(f"warning: {shorten(note)}")
    return "\n".join(lines) + "\n"


def write_cluster_outputs(result, folder: Path, *, pictures: bool = True) -> list[Path]:
    """Write layout.json, summary.txt and (``pictures``) the per-region heatmaps and the layout +
    regions pictures into ``folder``."""
    from mocaptk.atomic import write_text
    from mocaptk.clustering.layout import write_layout

    layout = result.layout
    written = [write_layout(layout, folder / "layout.json"),
               write_text(folder / "summary.txt", summary_text(result))]
    if pictures:  # matplotlib: most of the time of a --formats none run on a long session
        written += write_cluster_pictures(result, folder)
    return written


def write_cluster_pictures(result, folder: Path) -> list[Path]:
    """correlation_<region>.png per region, layout.png and regions.png in ``folder``."""
    import numpy as np

    from mocaptk.clustering.figures import correlation_heatmap, layout_picture, regions_picture

    layout = result.layout
    written = []
    # boxes: the layout's influence regions (the paper's clusters only with --method paper)
    influence = {m: k for k, c in enumerate(layout.clusters) if c.mirrored_from is None for m in c.members}
    representatives = [c.representative for c in layout.clusters]
    for name, region in result.matrices.items():
        boxes = np.array([influence.get(label, len(layout.clusters)) for label in region.labels])
        foreign = [f"{label} by {layout.clusters[k].representative} ({layout.clusters[k].region})"
                   for label, k in zip(region.labels, boxes) if k < len(layout.clusters)
                   and layout.clusters[k].region != name]
        pairs = [", ".join(foreign[i:i + 2]) for i in range(0, min(len(foreign), 4), 2)]  # fits a 2-marker map
        elsewhere = "\nfollowed from another region:\n" + "\n".join(pairs) + (" ..." if len(foreign) > 4 else "")
        written.append(correlation_heatmap(region.labels, region.matrix, boxes,
                                           title=f"{name}: consolidated correlation, boxed by the layout's\n"
                                                 "influence regions (representatives in bold)"
                                                 + (elsewhere if foreign else ""),
                                           representatives=representatives,
                                           path=folder / f"correlation_{name}.png"))
    traj = result.trajectories
    frame = result.frame
    neutral = dict(zip(traj.labels, result.neutral))
    written.append(layout_picture(layout, neutral, frame=frame, path=folder / "layout.png"))
    regions = {r.name: list(r.markers) for r in layout.regions}
    written.append(regions_picture(regions, neutral, frame=frame, path=folder / "regions.png"))
    return written


@app.command()
def cluster(
    sessions: list[Path] = typer.Argument(..., metavar="SESSION", help="Dense session file (C3D, "
                                          "Vicon CSV, TRC, generic CSV, npz); several: one actor each, "
                                          "one layout for all (registered to the first)."),
    factor: float = typer.Option(1.1, "--factor", help="Refinement factor (> 0): threshold = factor x "
                                 "region mean correlation; larger gives more markers."),
    method: str = typer.Option("hybrid", "--method", help="Layout method choosing the measured markers: "
                               "hybrid (default, the best on held-out data), paper (the paper's "
                               "representatives: Will, De Martino & Bezerra as written), qr, greedy, "
                               "kmeans, thin-shell, set-cover, robust, farthest-point, random. The paper's rule "
                               "at --factor sets the count and the influence regions (see mocaptk compare)."),
    rig: str = typer.Option(None, "--rig", help="Camera rig the layout is for: cara, room or a rig "
                            "file; the method then avoids markers the rig sees badly or triangulates "
                            "noisily (see mocaptk plan). Not with --method paper."),
    character: str = typer.Option(None, "--character", help="With --method set-cover: cover this "
                                  "blendshape rig's shapes (arkit, or a .glb/.fbx/.usd as in mocaptk "
                                  "retarget) mapped to the session's markers, instead of the session's "
                                  "extreme frames (Zell & McDonnell)."),
    markers: int = typer.Option(None, "--markers", help="Exactly N measured markers (mirrored twins come "
                                "on top) instead of the count the paper's rule gives at --factor."),
    regions: Path = typer.Option(None, "--regions", help="Regions file: JSON {region: list of labels} "
                                 "or CSV label,region (default: label prefixes, else geometric)."),
    takes: Path = typer.Option(None, "--takes", help="Takes file {\"takes\": [{name, region, start, end}]} "
                               "(default: takes recorded in the session)."),
    step: int = typer.Option(5, "--step", help="Use every STEP-th frame for the correlation matrices."),
    out: Path = typer.Option(None, "--out", help="Output folder (default: <session>_layout/ next to it)."),
    mirror: bool = typer.Option(None, "--mirror/--no-mirror", help="Mirror the half-face layout across "
                                "the sagittal plane (default: when labels show one half + midline)."),
    fill_gaps: bool = typer.Option(False, "--fill-gaps", help="Fill every gap from the session's main "
                                   "motion patterns (low-rank), once the head motion is removed, before "
                                   "clustering: for captures with many gaps, e.g. reconstructed from "
                                   "images, whose gaps follow the expression."),
    no_stabilize: bool = typer.Option(False, "--no-stabilize", help="Skip removing rigid head motion "
                                      "(for already head-relative data, e.g. head-mounted cameras)."),
    rigid: Rigid = None,
    rate: Rate = None,
    units: Units = None,
    force: bool = typer.Option(False, "--force", help="Replace an existing, non-empty output folder as a "
                               "whole: what else is in it goes too (e.g. evaluate's evaluation.json "
                               "and .html beside layout.json; write those elsewhere with evaluate --out)."),
    quiet: Quiet = False,
    mesh: Path = typer.Option(None, "--mesh", help="Character face mesh for the rig (OBJ, PLY, glTF; "
                              "default: a surface through the dense markers)."),
    max_influences: int = typer.Option(4, "--max-influences", help="Rig joints per vertex (1-8)."),
    formats: str = typer.Option("json,fbx,glb", "--formats", help="Rig files to write (json,fbx,glb) "
                                "with guide.pdf and the pictures; 'none' skips the rig, the guide "
                                "and the pictures (layout.json, summary.txt, report.html only)."),
    animate: list[Path] = typer.Option(None, "--animate", help="A performance to bake onto the "
                                       "rig after the session's own motion (as in mocaptk rig)."),
) -> None:
    """Dense session → minimal marker layout + influence regions (Will, De Martino & Bezerra).

    The influence regions are the paper's correlation clusters; the measured markers are chosen
    by the hybrid method unless --method paper.

    Writes the folder <session>_layout/ next to the session (or --out DIR): layout.json,
    summary.txt, report.html, pictures, rig files and guide.pdf (--formats none: the first three).
    With several sessions (actors), the layout is chosen on all of them pooled; the rig and
    pictures are the first actor's.
    """
    from rich.console import Console

    from mocaptk.clustering.pipeline import ClusterOptions, check_layout_options, cluster_session, load_session
    from mocaptk.clustering.regions import read_regions
    from mocaptk.clustering.takes import read_takes
    from mocaptk.background import beside

    from mocaptk.errors import OptionError
    from .rig import (animation_summary, check_summary, cluster_rig_outputs, parse_formats,
                      rig_options)

    session = sessions[0]
    if not factor > 0:  # options first: a bad value is reported, not the output folder
        raise OptionError(f"--factor must be > 0, got {factor}")
    if step < 1:
        raise OptionError(f"--step must be >= 1, got {step}")
    unknown_formats = [f for f in parse_formats(formats) if f not in ("json", "fbx", "glb", "none")]
    if unknown_formats:
        raise OptionError(f"--formats: unknown rig format(s) {', '.join(unknown_formats[:5])} (choose from json, fbx, glb, none)")
    given_rigid = rigid_labels(rigid) if not no_stabilize else None
    if given_rigid is not None and len(set(given_rigid)) < 3:
        raise OptionError(f"--rigid: stabilization needs at least 3 distinct rigid markers, got {len(set(given_rigid))}")
    rig_options(max_influences, None, False, 1)  # bad rig options fail before the slow part
    check_layout_options(method=method, markers=markers, rig=rig, shapes=character is not None)  # fail early
    if character is not None and len(sessions) > 1:
        raise OptionError("--character takes one session (the character is placed on its neutral)")
    if fill_gaps and len(sessions) > 1:
        raise OptionError("--fill-gaps takes one session")
    out_dir = claim_output(out or default_out_dir(session), force=force, folder=True,  # before the slow part
                           hint=OUT_HINT)
    console = Console(stderr=True, quiet=quiet)
    if len(sessions) > 1:
        if rig is not None:
            raise OptionError("--rig takes one session; several sessions (actors) with a rig are not supported")
        from mocaptk.clustering.multi_actor import load_actors
        actors, _, _, actor_sources = load_actors(sessions, None, stabilized=not no_stabilize, rate=rate,
                                                  units=units, rigid=rigid_labels(rigid))
        traj, source = actors[0], {k: actor_sources[0][k] for k in ("path", "sha256")}
    else:
        traj, source = load_session(session, rate=rate, units=units, layout_folder=out_dir)
        unknown = [label for label in given_rigid or () if label not in set(traj.labels)]
        if unknown:  # named here: from a batch sidecar the option is not on the user's command line
            raise OptionError(f"--rigid: {len(unknown)} labels are not markers of {session.name}: "
                              + ", ".join(unknown[:5]))
    # how the file was read, for evaluate, solve and rig to read it alike
    source = {**source, "reading": session_reading(traj, rate=rate, units=units)}
    if fill_gaps:  # solve, evaluate and rig read the raw session: say the layout saw it filled
        source["gaps_filled"] = "low-rank"
    neutral = None
    if len(sessions) == 1:  # one median pass for the face check and the layout
        import numpy as np

        from mocaptk.clustering.neutral import neutral_pose
        with np.errstate(all="ignore"):
            neutral = neutral_pose(traj.positions)
    warn_unless_face(traj, session, regions_given=regions is not None, neutral=neutral)
    shapes = None
    if character is not None:  # the rig's shapes at the session's markers (retarget's correspondence)
        from mocaptk.retarget.character_files import load_character
        from mocaptk.retarget.correspondence import correspond
        rig_face = load_character(character)
        shapes = (tuple(traj.labels), correspond(rig_face, neutral).shape_basis(rig_face))
    options = ClusterOptions(
        factor=factor, method=method, markers=markers, step=step, stabilize=not no_stabilize,
        mirror=mirror, rigid=rigid_labels(rigid), rig=rig, shapes=shapes,
        shapes_source=None if character is None else rig_face.source,
        regions=read_regions(regions, traj.labels) if regions else None,
        takes=read_takes(takes, traj.n_frames) if takes else None, fill_gaps=fill_gaps)
    with console.status("clustering") as status:
        if len(sessions) > 1:
            from mocaptk.clustering.multi_actor import cluster_actors
            result = cluster_actors(actors, actor_sources, options=options, source=source,
                                    progress=lambda text: status.update(text))
        else:
            result = cluster_session(traj, options=options, source=source, neutral=neutral,
                                     progress=lambda text: status.update(text))
    for note in result.notes:
        warn(note)
    with staged_folder(out_dir, force=force) as folder:
        write_cluster_outputs(result, folder, pictures=False)
        pictures = parse_formats(formats) != ("none",)
        # the pictures in a second process while the rig is built: the same files, less waiting
        with beside((lambda: write_cluster_pictures(result, folder)) if pictures else None,
                    what="the pictures"):
            build = cluster_rig_outputs(result, folder, mesh=mesh, max_influences=max_influences,
                                        formats=formats, quiet=quiet, session=traj,
                                        animate=animate or [])
        summary = summary_text(result)
        if build is not None:  # the rig's check (per region, held-out captures) after the header
            summary += "\n".join([f"rig: {build.rig.joint_count - 1} joints, skinning check RMSE "
                                  f"{build.check.rmse_mm:.2f} mm; guide.pdf written",
                                  check_summary(build.report),
                                  animation_summary(build.report["animation"])]) + "\n"
        report = write_cluster_report(result, build, folder / "report.html", summary=summary)
    if not quiet:  # the warnings were printed as they came (stderr): summary.txt keeps them, not stdout
        typer.echo("".join(line for line in summary.splitlines(True) if not line.startswith("warning: ")), nl=False)
        typer.echo(report)
        typer.echo(f"wrote {out_dir}/ ({len(result.layout.clusters)} layout markers)")
