"""Which of a view's sightings go into the graph while a module is measured: its own tags', and
those of the `k` other tags nearest it.

A view 2.2 m out reads tags up to 4 m away, ~17 a view at N = 8, all over the structure; each
sighting of a far tag makes iSAM2 re-eliminate that tag's path to the Bayes tree's root, while the
module's 1-sigma comes from its own tags and the camera, which its neighbours and the rig chain
place.  Replayed on the runs' own detections (docs/sf_graphslam.md, "What a view gives the
graph"): k = 5 cut an N = 8 run's step CPU 2.1x and kept 27 % of its sightings, 10 runs at N = 3
kept 71-72 %; no verdict changed in either, the good modules' 1-sigma grew 0.3 % (median), 3.5 %
at most.  A nearest count, not a radius: 1 m cut the N = 8 step 2.4x but grew some 1-sigma 26 %
and turned two N = 3 faults `uncertain`.  Leaving data out keeps the 1-sigma honest (the same
maximum-likelihood solve over fewer measurements); the run's log keeps every detection."""

from __future__ import annotations

from typing import Protocol, Sequence, TypeVar

import numpy as np

from lab.core.structures.borg import BorgModel


class Sighting(Protocol):
    tag_id: int


D = TypeVar("D", bound=Sighting)   # estimation.fiducials.Detection


def near_sightings(model: BorgModel, module: str, sightings: Sequence[D], k: int) -> list[D]:
    """`sightings` (in their order) of `module`'s own tags and of the `k` other tags nearest its
    tags (design positions; the id breaks a tie, so a replay picks the same); k <= 0: all of them.
    An id the model does not know stays: the estimator's own check refuses it."""
    mod = model.module_by_name.get(module)
    if k <= 0 or mod is None:
        return list(sightings)
    mine = set(mod.tags)
    others = {s.tag_id for s in sightings if s.tag_id not in mine and s.tag_id in model.tags}
    if len(others) <= k:
        return list(sightings)
    own = np.array([model.tags[t].structure_T_tag.translation() for t in mod.tags]).reshape(-1, 3)
    gap = {}
    for t in others:
        delta = own - model.tags[t].structure_T_tag.translation()
        gap[t] = float(np.min(np.einsum("ij,ij->i", delta, delta)))
    near = set(sorted(gap, key=lambda t: (gap[t], t))[:k])
    return [s for s in sightings if s.tag_id in mine or s.tag_id in near or s.tag_id not in model.tags]
