"""Upper-lid joints that close the default face's eyes when the actor blinks.

A dense session has no marker on the eyelid, but the layout's eye-region markers under the
brow move with it (sample: EYE_08_L 5.7 mm down at a full blink, correlation 0.85 with the true
blink weight). Per eye:

- the **blink** ``b(t)`` in [0, 1] is the least-squares fraction of the full-blink displacement
  (:class:`~mocaptk.retarget.default_face.Lid`) that the eye's *sensor* markers (layout markers
  that a full blink moves more than :data:`SENSOR_MIN_MM`) show, over the fraction they show at
  the session's fullest blinks (its :data:`FULL_PERCENTILE`: the dense session's eye take
  blinks);
- the **lid joint** sits at the upper rim's centre; it follows the markers as the rim's own
  weights would (``follow``) and adds ``b(t)`` times the rim's full-blink displacement less
  what following makes of a full blink (the markers near the eye move with the blink: counted
  twice, the lid overshot the lower rim and folded);
- each vertex's weight on it is the fraction of the rim's full blink its own full-blink
  displacement is, and its other weights shrink to leave room.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .default_face import Lid

__all__ = ["LidJoints", "lid_joints"]

#: A layout marker senses a blink when a full blink moves its vertex more than this (mm).
SENSOR_MIN_MM = 1.0
#: Percentile of the sensed blink over the session taken as a full blink.
FULL_PERCENTILE = 99.5
#: A session whose sensed blink never reaches this fraction of the template's has no blink to
#: calibrate on (the template's full blink is kept).
MIN_FULL = 0.3
#: Lid weights below this are dropped (the lid's influence ends smoothly before it).
MIN_LID_WEIGHT = 0.01


@dataclass(frozen=True, eq=False)
class LidJoints:
    """Per eye (E eyes): ``positions`` (E, 3) mm bind positions, ``follow`` (E, L) weights over
    the layout joints, ``closed`` (E, 3) mm the displacement a full blink adds to following, and the sensors:
    ``sensor_index`` (E,) arrays of layout joints with ``sensor_blink`` (E,) arrays (S, 3) mm,
    their displacement at a full blink."""

    positions: np.ndarray
    follow: np.ndarray
    closed: np.ndarray
    sensor_index: tuple[np.ndarray, ...]
    sensor_blink: tuple[np.ndarray, ...]
    full: np.ndarray | None = None

    def sensed(self, displacement: np.ndarray) -> np.ndarray:
        """The fraction (F, E) of the full-blink displacement the sensors show (least squares,
        unclipped) for the layout joints' displacements (F, L, 3) mm."""
        out = np.zeros((displacement.shape[0], len(self.positions)))
        for e, (index, full) in enumerate(zip(self.sensor_index, self.sensor_blink)):
            if len(index):
                seen = np.einsum("fsk,sk->f", displacement[:, index], full)
                out[:, e] = seen / float(np.sum(full * full))
        return out

    def calibrated(self, displacement: np.ndarray) -> LidJoints:
        """These joints with the full blink of each eye taken as the :data:`FULL_PERCENTILE`
        of :meth:`sensed` over the session ``displacement`` (F, L, 3) mm (its eye take has
        full blinks), when that is above :data:`MIN_FULL` (else the template's own)."""
        sensed = self.sensed(displacement)
        full = np.array([np.nanpercentile(column, FULL_PERCENTILE) if np.isfinite(column).any()
                         else np.nan for column in sensed.T])
        return replace(self, full=np.where(full > MIN_FULL, full, 1.0))

    def blink(self, displacement: np.ndarray) -> np.ndarray:
        """Blink (F, E) in [0, 1] from the layout joints' displacements (F, L, 3) mm."""
        full = np.ones(len(self.positions)) if self.full is None else self.full
        return np.clip(self.sensed(displacement) / full, 0.0, 1.0)

    def displacements(self, displacement: np.ndarray) -> np.ndarray:
        """The lid joints' displacements (F, E, 3) mm from the layout joints' (F, L, 3) mm (NaN
        where a marker it uses is missing)."""
        used = self.follow.any(axis=0)
        for index in self.sensor_index:
            used[index] = True
        displacement = np.where(used[None, :, None], displacement, 0.0)  # others' gaps: no matter
        follow = np.einsum("el,flk->fek", self.follow, displacement)
        return follow + self.blink(displacement)[..., None] * self.closed


def lid_joints(vertices: np.ndarray, lids: tuple[Lid, ...], weights: np.ndarray, *,
               joint_vertices: np.ndarray, displacement: np.ndarray) -> tuple[LidJoints, np.ndarray]:
    """The joints of the ``lids`` of a face mesh (``vertices`` (V, 3) mm: the default face's, or a
    ``--mesh`` with eye openings) and the dense weights (V, L + E) with them, before capping:
    ``weights`` (V, L) over the L layout joints (``joint_vertices`` (L,) their vertices; the
    session's ``displacement`` (F, L, 3) mm calibrates the full blink); the lid joints become
    joints L, L + 1... A vertex's lid weight is what its markers do not make of its full-blink
    displacement, as a fraction of the rim's, and its other weights shrink to leave room
    (capped with the rest afterwards: no influence is dropped out of turn)."""
    dense = np.asarray(weights, dtype=float)
    sensors = [np.flatnonzero(np.linalg.norm(lid.blink[joint_vertices], axis=1) > SENSOR_MIN_MM)
               for lid in lids]
    uncalibrated = LidJoints(np.zeros((len(lids), 3)), np.zeros((len(lids), len(dense[0]))),
                             np.zeros((len(lids), 3)), tuple(sensors),
                             tuple(lid.blink[joint_vertices[s]] for lid, s in zip(lids, sensors)))
    calibrated = uncalibrated.calibrated(displacement).full
    lid_weight = np.zeros((len(vertices), len(lids)))
    positions, follow, closed = [], [], []
    for e, lid in enumerate(lids):
        # the rim's farthest move: every vertex's lid weight stays within [0, 1]
        full = lid.blink[lid.upper][int(np.argmax(np.linalg.norm(lid.blink[lid.upper], axis=1)))]
        # what the markers make of a full blink (they show `calibrated` of the template's), and
        # the lid the rest: a vertex's lid weight w is least squares for (1 - w) own + w full =
        # its blink
        markers = calibrated[e] * lid.blink[joint_vertices]
        own = dense @ markers
        gap = full - own
        lid_weight[:, e] = np.clip(np.einsum("vk,vk->v", lid.blink - own, gap)
                                   / np.maximum(np.einsum("vk,vk->v", gap, gap), 1e-12), 0.0, 1.0)
        positions.append(vertices[lid.upper].mean(axis=0))
        follow.append(dense[lid.upper].mean(axis=0))
        closed.append(full - follow[-1] @ markers)  # the lid follows the markers too
    lid_weight[lid_weight < MIN_LID_WEIGHT] = 0.0
    keep = 1.0 - lid_weight.max(axis=1)  # one lid per vertex: the eyes are far apart
    lid_weight[lid_weight < lid_weight.max(axis=1, keepdims=True)] = 0.0
    joints = replace(uncalibrated, positions=np.array(positions), follow=np.array(follow),
                     closed=np.array(closed), full=calibrated)
    return joints, np.column_stack([dense * keep[:, None], lid_weight])
