"""The batch solve's view factors evaluated together: every view's corner errors, and at a
linearisation every view's Jacobian, in one compiled call at a point instead of one Python callback
a view.

`rig_model.corner_view_factor` gave the batch one factor for a view's tags (since, up to
`TAGS_PER_FACTOR` of them).  Levenberg-Marquardt evaluates the graph's error at its start and at
every trial step, and linearises it once an iteration; through the factors that is one callback a
factor each time (~12 us of callback, numba dispatch and pose reads for a few us of arithmetic: at
8x8x8, 1,230 views, ~20 ms an error evaluation).  A `ViewBatch`
keeps every view's constants in flat arrays (`rig_model.ViewLayout`, concatenated):

- `error` is the views' part of the graph's error, 0.5 |e|^2 summed, from one call of
  `corner_kernel.batch_view_errors`, with no factor called back;
- `prepare` computes every view's error and Jacobian the same way before GTSAM linearises the graph;
  each view's factor (`add`) then hands GTSAM its rows from the batch's buffers.

The numbers are the view factors' own (`corner_kernel.view_errors`, called for each view in turn):
the same linear system to the bit.  A factor called with values the batch was not prepared at
computes its rows itself, as a `corner_view_factor` does, so an unprepared batch costs time, never
correctness.  `BatchCost` is the graph's cost as `levenberg_marquardt.optimize` takes it: the graph's
other factors evaluated by GTSAM, the views by the batch.

Left out: the intrinsics as a variable (a view factor fixes them, as the run's graph does)."""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from estimation import corner_kernel
from estimation.rig_model import (CornerSighting, PoseTable, ViewLayout, _cal_vector, behind_rows, view_error_function,
                                  view_layout)


# tags a view factor takes at most (`SfGraphSlam._batch_graph` splits a view's tags into factors of
# this many): a factor's Jacobian is one dense block over its camera and all its tags, and GTSAM's
# elimination multiplies its zero blocks (tag i's rows against tag j's columns), while each factor
# is one callback a linearisation.  The scaling study's surveys, Levenberg-Marquardt paired in one
# process: 3 tags a factor against a whole view (6.2 tags on average at N = 8) 297 against 397 ms at
# N = 8, 68 against 74 at N = 5, 13.0 against 14.1 at N = 3; 2 tags 311 ms and 4 tags 327 at N = 8,
# 1 tag a factor (7,577 callbacks) 399 against a whole view's 414
TAGS_PER_FACTOR = 3


class ViewBatch:
    """The view factors of one batch graph (`add` each), evaluated together at a point (`prepare`,
    `error`) read from its pose table, which the solve `track`s."""

    def __init__(self, fixed: gtsam.Cal3_S2) -> None:
        self.cal = _cal_vector(fixed)
        self.fixed = fixed
        self.table = PoseTable()
        self.layouts: list[ViewLayout] = []
        self.values: gtsam.Values | None = None     # the point `prepare` last evaluated the views at
        self.jacobians = False                      # ... and whether with their Jacobians
        self._built = 0                             # views the flat arrays hold
        self._generation = -1                       # the table generation the rows are of
        self._scale_keys = np.zeros(0, np.uint64)   # the scale variables the values hold, in key order

    def add(self, camera_key: int, sightings: Sequence[CornerSighting], robust_k: float | None,
            lens_key: int | None = None) -> gtsam.CustomFactor:
        """One view's factor (`rig_model.corner_view_factor`'s), its rows from the batch when the
        batch was prepared at the values it is called with."""
        layout = view_layout(camera_key, sightings, robust_k, lens_key)
        v = len(self.layouts)
        self.layouts.append(layout)
        batch = self
        own: list = []          # the factor's own error function, made if it is ever called unprepared

        def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[np.ndarray] | None) -> np.ndarray:
            # a linearisation's rows are reweighted for Huber unlike an error's (`whiten_rows`):
            # only what was prepared for this very call is handed back
            if batch.values is values and batch.jacobians == (jacobians is not None) and v < batch._built:
                if jacobians is not None:
                    for j, block in enumerate(batch._blocks[v]):
                        jacobians[j] = block
                return batch._errors[v]
            if not own:
                own.append(view_error_function(layout, batch.fixed, batch.table))
            return own[0](this, values, jacobians)

        return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(8 * len(layout.sightings)), list(layout.keys), error)

    # ---- the flat arrays --------------------------------------------------------------------------------
    def _build(self) -> None:
        """The flat arrays and buffers of every view added so far (after an `add`: the graph grows
        between solves)."""
        layouts = self.layouts
        self._first_tag = np.cumsum([0] + [len(x.sightings) for x in layouts]).astype(np.int64)
        self._first_J = np.cumsum([0] + [8 * len(x.sightings) * x.width for x in layouts]).astype(np.int64)
        self._consts = np.concatenate([x.consts for x in layouts])
        self._inverse_sigma = np.concatenate([x.inverse_sigma for x in layouts])
        self._columns = np.concatenate([x.columns for x in layouts])
        self._huber_k = np.array([x.huber_k for x in layouts])
        self._lensed = np.array([x.lens_key is not None for x in layouts], np.bool_)
        lens_keys = {x.lens_key for x in layouts if x.lens_key is not None}
        if len(lens_keys) > 1:
            raise ValueError("a view batch reads one lens variable")
        self._lens_key = next(iter(lens_keys), None)
        self._tag_keys = [s.tag_key for x in layouts for s in x.sightings]
        self._sighting_scale_keys = np.array([0 if s.scale_key is None else s.scale_key
                                              for x in layouts for s in x.sightings], np.uint64)
        self._has_scale = np.array([s.scale_key is not None for x in layouts for s in x.sightings], np.bool_)
        self._ok = np.empty(len(self._tag_keys), np.bool_)
        self._e = np.empty(8 * len(self._tag_keys))
        self._J = np.zeros(int(self._first_J[-1]))
        self._errors, self._blocks = [], []
        for v, x in enumerate(layouts):
            t0, t1 = self._first_tag[v], self._first_tag[v + 1]
            self._errors.append(self._e[8 * t0:8 * t1])
            J = self._view_J(v)
            self._blocks.append([J[:, x.starts[j]:x.starts[j + 1]] for j in range(len(x.keys))])
        self._built = len(layouts)
        self._generation = -1

    def _view_J(self, v: int) -> np.ndarray:
        """View v's Jacobian (8 n, width), column-major in the flat buffer (`batch_view_errors`)."""
        x = self.layouts[v]
        return self._J[self._first_J[v]:self._first_J[v + 1]].reshape(x.width, 8 * len(x.sightings)).T

    def _rows(self) -> None:
        """Each view's camera and each sighting's tag as rows of the table (when the table's keys change)."""
        row = self.table.row
        self._camera_rows = np.array([row[x.camera_key] for x in self.layouts], np.int64)
        self._tag_rows = np.array([row[k] for k in self._tag_keys], np.int64)
        self._generation = self.table.generation

    def track(self, values: gtsam.Values) -> None:
        """A solve from `values` begins: the table holds its poses, the batch its scale variables."""
        self.table.track(values)
        self.values = None
        if self._built != len(self.layouts):
            self._build()
        if self._has_scale.any():
            keys = np.array(values.keys(), np.uint64)
            self._scale_char = gtsam.Symbol(int(self._sighting_scale_keys[self._has_scale][0])).chr()
            keys = np.sort(keys[(keys >> np.uint64(56)) == np.uint64(self._scale_char)])
            if not np.array_equal(keys, self._scale_keys):
                self._scale_keys = keys
                self._generation = -1
        else:
            self._scale_keys = np.zeros(0, np.uint64)

    def release(self) -> None:
        """The solve is over: nothing prepared, the table unloaded."""
        self.values = None
        self.table.clear()

    def prepare(self, values: gtsam.Values, jacobians: bool) -> None:
        """Every view's error (and with `jacobians` its Jacobian) at `values`, which hold the
        tracked poses; the views' factors called with `values` hand these back."""
        if self._built != len(self.layouts):
            raise RuntimeError("views were added after the solve began: track the values again")
        self.table.load(values)
        if self._generation != self.table.generation:
            self._rows()
            # each sighting's print scale as a row of the values' scale variables (GTSAM would
            # refuse a missing one; the batch reads them itself, so it checks)
            at = np.searchsorted(self._scale_keys, self._sighting_scale_keys)[self._has_scale]
            if at.size and (at.max() >= len(self._scale_keys) or
                            not np.array_equal(self._scale_keys[at], self._sighting_scale_keys[self._has_scale])):
                raise ValueError("a view factor's print-scale variable is not in the values")
            self._scale_rows = np.full(len(self._has_scale), -1, np.int64)
            self._scale_rows[self._has_scale] = at
        # every scale variable in one call: `extractVectors` returns them in key order
        scales = (gtsam.utilities.extractVectors(values, chr(self._scale_char))[:, 0] if len(self._scale_keys)
                  else np.zeros(0))
        if len(scales) != len(self._scale_keys):
            raise ValueError("the values' scale variables changed while a solve was on")
        lens = np.zeros(0) if self._lens_key is None else np.ascontiguousarray(values.atVector(self._lens_key))
        self.values = None
        if corner_kernel.batch_view_errors(self.table.poses, self._camera_rows, self._tag_rows, self._scale_rows, scales,
                                           lens, self._lensed, self.cal, self._consts, self._inverse_sigma,
                                           self._huber_k, jacobians, self._e, self._J, self._columns,
                                           self._first_tag, self._first_J, self._ok):
            self._behind(values, scales, lens, jacobians)
        self.values, self.jacobians = values, jacobians

    def _behind(self, values: gtsam.Values, scales: np.ndarray, lens: np.ndarray, want: bool) -> None:
        """The rows the kernel left (a corner on or behind its camera's plane), view by view."""
        for v in np.unique(np.searchsorted(self._first_tag, np.flatnonzero(~self._ok), side="right") - 1):
            t0, t1 = self._first_tag[v], self._first_tag[v + 1]
            x = self.layouts[v]
            rows = self._scale_rows[t0:t1]
            sc = np.zeros(t1 - t0)
            sc[rows >= 0] = scales[rows[rows >= 0]]
            J = self._view_J(v)
            behind_rows(x, values, sc, lens if x.lens_key is not None else np.zeros(0), self.cal,
                        self._ok[t0:t1], self._errors[v], J, want)

    def error(self, values: gtsam.Values) -> float:
        """The view factors' share of the graph's error at `values` (each 0.5 |e|^2)."""
        self.prepare(values, False)
        return 0.5 * float(self._e @ self._e)


class BatchCost:
    """A batch graph's error and linearisation for `levenberg_marquardt.optimize`: `others` (the
    graph's factors that are not the batch's views) evaluated by GTSAM, the views by `batch`."""

    def __init__(self, graph: gtsam.NonlinearFactorGraph, others: gtsam.NonlinearFactorGraph, batch: ViewBatch) -> None:
        self.graph, self.others, self.batch = graph, others, batch

    def error(self, values: gtsam.Values) -> float:
        return self.others.error(values) + self.batch.error(values)

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        self.batch.prepare(values, True)
        return self.graph.linearize(values)
