"""A spatial index of field-of-view polygons that stays fast while cameras come, go and move.

Why this design: shapely 1.8's ``STRtree`` (GEOS, C) answers a query among a
million polygons in tens of microseconds, but it is static — it cannot take an
insertion or a deletion, and building one over 1,000,000 polygons takes seconds.
Cameras register, move and expire all the time, so the index is a log-structured
pair:

- a **tree**: an STRtree over a snapshot of the polygons;
- a **delta**: the polygons inserted or moved since that snapshot, scanned by
  their bounding boxes.

A tree item whose key was removed or moved since the snapshot is recognised
(its polygon object is no longer the current one for its key) and skipped.
When the delta plus the stale items pass a threshold (about 1 % of the index,
between 256 and 4096), a new tree is built from a fresh snapshot — in a
background thread by default, so registrations and queries never wait for a
rebuild; changes made during the build stay in the delta. A query therefore
costs one tree query plus a bounding-box scan of at most a few thousand delta
entries, whatever the size of the index (see ``bench/bench_matching.py``).

(Debian's python3-rtree would give a dynamic R-tree, but one-by-one insertion of
a million entries is slower than an STRtree bulk build, and it adds a dependency.)

Matching rule: :func:`interiors_intersect`. A field of view matches a region
when their *interiors* share a point (DE-9IM ``T********``): overlapping by any
positive area matches; touching along an edge or at a corner only does not
(the camera would see nothing of the region but a line). A region of zero
width (a segment or a point) matches the fields of view whose interior it
enters.

The index is thread-safe (one internal lock).
"""

from __future__ import annotations

import logging
import threading
import warnings
from collections.abc import Hashable

from shapely.errors import ShapelyError
from shapely.geometry.base import BaseGeometry
from shapely.prepared import prep
from shapely.strtree import STRtree

logger = logging.getLogger('rosout.' + __name__)

__all__ = ['FieldOfViewIndex', 'interiors_intersect']


def interiors_intersect(field_of_view: BaseGeometry, region: BaseGeometry) -> bool:
    """True if the interiors of the two geometries share at least one point.

    GEOS's relate is not robust for every valid input (a region corner on a
    vertex rounded to float32 can raise "side location conflict"); then the
    answer falls back to intersection (prepared geometry, another algorithm),
    and at last to overlapping bounds. Both may also count touching edges: a
    request forwarded to one camera too many costs little, a lost request costs
    a robot its answer.
    """
    try:
        return field_of_view.relate_pattern(region, 'T********')
    except ShapelyError as error:
        logger.warning('relate failed (%s); matching by intersection instead', error)
    try:
        return prep(field_of_view).intersects(region)
    except ShapelyError as error:
        logger.warning('intersection failed too (%s); matching by bounds', error)
        return _boxes_overlap(field_of_view.bounds, region.bounds)


def _boxes_overlap(a: tuple, b: tuple) -> bool:
    return a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]


def _build_tree(items: list[tuple[Hashable, BaseGeometry]]) -> STRtree | None:
    if not items:
        return None
    with warnings.catch_warnings():
        # shapely 1.8 warns that 2.0 will drop ``items``; this project pins 1.8 (Debian bookworm).
        warnings.simplefilter('ignore')
        return STRtree([geometry for _, geometry in items], range(len(items)))


class FieldOfViewIndex:
    """Polygons by key; :meth:`query` returns the keys whose polygon interior meets a region.

    :param background: rebuild the tree in a background thread (True) or inline
        in the call that crossed the threshold (False: deterministic, for tests).
    :param min_rebuild: delta + stale items that trigger a rebuild, at least.
    :param max_rebuild: ... and at most (the cap on the linear scan's length).
    """

    def __init__(self, background: bool = True, min_rebuild: int = 256, max_rebuild: int = 4096):
        self.background = background
        self.min_rebuild = min_rebuild
        self.max_rebuild = max_rebuild
        self._lock = threading.Lock()
        self._current: dict[Hashable, BaseGeometry] = {}
        self._bounds: dict[Hashable, tuple] = {}
        self._delta: dict[Hashable, BaseGeometry] = {}
        self._tree: STRtree | None = None
        self._tree_items: list[tuple[Hashable, BaseGeometry]] = []
        self._stale = 0  # tree items whose key was removed or moved since the snapshot
        self._version = 0  # bumped on every change
        self._changed: set = set()  # keys inserted or removed since the tree's snapshot
        self._building: threading.Thread | None = None
        self.rebuilds = 0

    def __len__(self) -> int:
        return len(self._current)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._current

    def get(self, key: Hashable) -> BaseGeometry | None:
        return self._current.get(key)

    # -- changes -----------------------------------------------------------------------------
    def insert(self, key: Hashable, geometry: BaseGeometry) -> None:
        """Add ``key`` or replace its polygon."""
        with self._lock:
            if key in self._current and key not in self._delta:
                self._stale += 1  # its tree item is now out of date
            self._current[key] = geometry
            self._changed.add(key)
            self._bounds[key] = geometry.bounds
            self._delta[key] = geometry
            self._version += 1
            self._maybe_rebuild()

    def remove(self, key: Hashable) -> bool:
        """Remove ``key``; False if it was not there."""
        with self._lock:
            if key not in self._current:
                return False
            del self._current[key]
            del self._bounds[key]
            self._changed.add(key)
            if self._delta.pop(key, None) is None:
                self._stale += 1
            self._version += 1
            self._maybe_rebuild()
            return True

    # -- queries -----------------------------------------------------------------------------
    def candidates(self, bounds: tuple) -> list[Hashable]:
        """Keys whose polygon's bounding box meets ``bounds`` (min_x, min_y, max_x, max_y)."""
        from shapely.geometry import box

        with self._lock:
            tree, items, current, delta = self._tree, self._tree_items, self._current, self._delta
            found = []
            if tree is not None:
                for index in tree.query_items(box(*bounds)):
                    key, geometry = items[index]
                    if current.get(key) is geometry and key not in delta:
                        found.append(key)
            bounds_of = self._bounds
            found.extend(key for key in delta if _boxes_overlap(bounds_of[key], bounds))
            return found

    def query(self, region: BaseGeometry) -> list[Hashable]:
        """Keys whose polygon's interior meets ``region``'s interior (:func:`interiors_intersect`)."""
        keys = self.candidates(region.bounds)
        with self._lock:
            pairs = [(key, self._current.get(key)) for key in keys]
        return [
            key for key, geometry in pairs if geometry is not None and interiors_intersect(geometry, region)
        ]

    # -- rebuilding --------------------------------------------------------------------------
    def _threshold(self) -> int:
        return max(self.min_rebuild, min(self.max_rebuild, len(self._current) // 100))

    def _maybe_rebuild(self) -> None:
        """Called with the lock held: start a rebuild if the delta and stale items grew too many."""
        if len(self._delta) + self._stale < self._threshold() or self._building is not None:
            return
        snapshot = self._snapshot()
        if self.background:
            self._building = threading.Thread(
                target=self._rebuild, args=(snapshot,), name='fov-index-rebuild', daemon=True
            )
            self._building.start()
        else:
            self._install(snapshot, _build_tree(snapshot), dict(snapshot))

    def _snapshot(self) -> list:
        """Called with the lock held: the items of the next tree; changes are tracked from here."""
        self._changed = set()
        return list(self._current.items())

    def _rebuild(self, snapshot: list) -> None:
        tree, in_tree = _build_tree(snapshot), dict(snapshot)
        with self._lock:
            self._install(snapshot, tree, in_tree)
            self._building = None
            logger.debug('field-of-view index rebuilt: %d polygons', len(snapshot))
            self._maybe_rebuild()

    def _install(self, snapshot: list, tree: STRtree | None, in_tree: dict) -> None:
        """Called with the lock held: the snapshot becomes the tree; the delta keeps newer changes."""
        self._tree, self._tree_items = tree, snapshot
        self._delta = {key: g for key, g in self._delta.items() if in_tree.get(key) is not g}
        # Every snapshot key changed (moved or removed) since the snapshot has a stale tree item.
        self._stale = sum(1 for key in self._changed if key in in_tree)
        self.rebuilds += 1

    def wait_for_rebuild(self, timeout: float | None = None) -> None:
        """Wait for a background rebuild in progress, if any (for tests and benchmarks)."""
        building = self._building
        if building is not None:
            building.join(timeout)

    def rebuild_now(self) -> None:
        """Build the tree from everything now (inline), e.g. after a bulk load."""
        self.wait_for_rebuild()
        with self._lock:
            snapshot = self._snapshot()
        tree, in_tree = _build_tree(snapshot), dict(snapshot)
        with self._lock:
            self._install(snapshot, tree, in_tree)
