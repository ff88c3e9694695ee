"""Pointers between frames as typed relations with a time of validity.

Reference 001, section 4.4.2 (inheritance and situational pointers, Figures 18 and 19) and
sections 4.4.8-4.4.9 (event parent/sub-events, before/after/simultaneous-with, causes,
entities involved). A relation ``src --kind--> dst`` is valid over
``[t_from_ns, t_to_ns)``; ``t_to_ns`` None means still valid. Paired kinds are stored both
ways and always change together (belongs_to/has_part, on_top_of/beneath,
in_front_of/behind, before/after); symmetric kinds (beside, near, simultaneous_with) likewise.
``is_a`` and ``appears_in`` are the class and image pointers held in the entity frame
(``generic_classes``, ``specific_class``, ``images``); the ``relations`` SQL view lists them
with the frame-to-frame pointers.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, replace
from enum import StrEnum

from kd_store.errors import KDError


class RelationKind(StrEnum):
    BELONGS_TO = "belongs_to"
    HAS_PART = "has_part"
    IS_A = "is_a"
    APPEARS_IN = "appears_in"
    ON_TOP_OF = "on_top_of"
    BENEATH = "beneath"
    BESIDE = "beside"
    IN_FRONT_OF = "in_front_of"
    BEHIND = "behind"
    INSIDE_OF = "inside_of"
    NEAR = "near"
    BEFORE = "before"
    AFTER = "after"
    DURING = "during"
    SIMULTANEOUS_WITH = "simultaneous_with"
    CAUSES = "causes"
    INVOLVES = "involves"


K = RelationKind
INVERSE: dict[RelationKind, RelationKind] = {
    K.BELONGS_TO: K.HAS_PART,
    K.HAS_PART: K.BELONGS_TO,
    K.ON_TOP_OF: K.BENEATH,
    K.BENEATH: K.ON_TOP_OF,
    K.IN_FRONT_OF: K.BEHIND,
    K.BEHIND: K.IN_FRONT_OF,
    K.BEFORE: K.AFTER,
    K.AFTER: K.BEFORE,
    K.BESIDE: K.BESIDE,
    K.NEAR: K.NEAR,
    K.SIMULTANEOUS_WITH: K.SIMULTANEOUS_WITH,
}
#: Kinds held as frame fields, not graph edges.
FIELD_KINDS = frozenset({K.IS_A, K.APPEARS_IN})


@dataclass(frozen=True, slots=True)
class Relation:
    """``src --kind--> dst`` valid over ``[t_from_ns, t_to_ns)`` (``t_to_ns`` None: open)."""

    src: int
    kind: RelationKind
    dst: int
    t_from_ns: int
    t_to_ns: int | None = None

    def valid_at(self, t_ns: int | None) -> bool:
        """Valid at ``t_ns``; None asks whether it is open (valid now)."""
        if t_ns is None:
            return self.t_to_ns is None
        return self.t_from_ns <= t_ns and (self.t_to_ns is None or t_ns < self.t_to_ns)

    @property
    def key(self) -> tuple[int, str, int, int]:
        return (self.src, self.kind.value, self.dst, self.t_from_ns)


class RelationGraph:
    """Adjacency of relations by source and by destination; knows nothing of frame contents.

    The caller (the KD) checks that both ends exist; the graph keeps inverse pairs together,
    refuses belongs_to cycles and gives every child at most one open parent.
    """

    def __init__(self) -> None:
        self._out: dict[int, list[Relation]] = {}
        self._in: dict[int, list[Relation]] = {}
        self.dirty: set[tuple[int, str, int, int]] = set()

    # ------------------------------------------------------------------ reading

    def out(self, src: int, kind: RelationKind | None = None, t_ns: int | None = None) -> list[int]:
        """Destinations of ``src``'s relations of ``kind`` valid at ``t_ns`` (None: open now)."""
        return [
            r.dst
            for r in self._out.get(src, ())
            if (kind is None or r.kind == kind) and r.valid_at(t_ns)
        ]

    def inn(self, dst: int, kind: RelationKind | None = None, t_ns: int | None = None) -> list[int]:
        """Sources of relations of ``kind`` into ``dst`` valid at ``t_ns``."""
        return [
            r.src
            for r in self._in.get(dst, ())
            if (kind is None or r.kind == kind) and r.valid_at(t_ns)
        ]

    def relations_of(self, node: int) -> list[Relation]:
        """Every relation (open or closed) whose source is ``node``."""
        return list(self._out.get(node, ()))

    def relations_into(self, node: int) -> list[Relation]:
        """Every relation (open or closed) whose destination is ``node``."""
        return list(self._in.get(node, ()))

    def __iter__(self) -> Iterator[Relation]:
        for rels in self._out.values():
            yield from rels

    def __len__(self) -> int:
        return sum(len(r) for r in self._out.values())

    def parent(self, child: int, t_ns: int | None = None) -> int | None:
        p = self.out(child, K.BELONGS_TO, t_ns)
        return p[0] if p else None

    def ancestors(self, node: int, t_ns: int | None = None) -> list[int]:
        """Parent, grandparent, ... (nearest first)."""
        out: list[int] = []
        p = self.parent(node, t_ns)
        while p is not None:
            out.append(p)
            p = self.parent(p, t_ns)
        return out

    def parts_tree(self, root: int, t_ns: int | None = None) -> list[tuple[int, int]]:
        """(id, depth) of ``root`` and all its parts, depth first, parts in id order."""
        out: list[tuple[int, int]] = []
        stack = [(root, 0)]
        while stack:
            node, depth = stack.pop()
            out.append((node, depth))
            parts = sorted(self.out(node, K.HAS_PART, t_ns), reverse=True)
            stack.extend((p, depth + 1) for p in parts)
        return out

    def neighbourhood(
        self,
        node: int,
        kinds: Iterable[RelationKind] | None = None,
        depth: int = 1,
        t_ns: int | None = None,
    ) -> dict[int, int]:
        """Frames within ``depth`` hops of ``node`` over relations of ``kinds`` (either
        direction), as id -> hop count; ``node`` itself is not included."""
        kind_set = None if kinds is None else {RelationKind(k) for k in kinds}
        seen = {node: 0}
        queue = deque([node])
        while queue:
            n = queue.popleft()
            if seen[n] >= depth:
                continue
            for r in (*self._out.get(n, ()), *self._in.get(n, ())):
                if (kind_set is None or r.kind in kind_set) and r.valid_at(t_ns):
                    other = r.dst if r.src == n else r.src
                    if other not in seen:
                        seen[other] = seen[n] + 1
                        queue.append(other)
        del seen[node]
        return seen

    # ------------------------------------------------------------------ writing

    def check_add(self, src: int, kind: RelationKind, dst: int) -> None:
        """Refuse a relation that would make a self loop or a belongs_to cycle."""
        if kind in FIELD_KINDS:
            raise KDError(
                f"relation {src} {kind.value} {dst!r}: is_a and appears_in are held in the "
                "entity frame (generic_classes/specific_class, images), set them there"
            )
        if src == dst:
            raise KDError(f"relation {src} {kind.value} {dst}: a frame cannot point to itself")
        child, parent = (src, dst) if kind == K.BELONGS_TO else (dst, src)
        if kind in (K.BELONGS_TO, K.HAS_PART) and (
            parent == child or child in [parent, *self.ancestors(parent)]
        ):
            raise KDError(
                f"relation {src} {kind.value} {dst}: frame {child} is already an ancestor of "
                f"{parent}, so this would make a belongs_to cycle"
            )

    def add(self, src: int, kind: RelationKind, dst: int, t_from_ns: int) -> None:
        """Add ``src --kind--> dst`` (and its inverse), valid from ``t_from_ns``.

        An already-open identical relation is kept as is. A new parent closes the child's
        previous open parent at ``t_from_ns`` (re-grouping)."""
        kind = RelationKind(kind)
        self.check_add(src, kind, dst)
        if kind == K.HAS_PART:
            src, dst, kind = dst, src, K.BELONGS_TO
        if dst in self.out(src, kind):
            return
        if kind == K.BELONGS_TO:
            old = self.parent(src)
            if old is not None:
                self.close(src, K.BELONGS_TO, old, t_from_ns)
        inv = INVERSE.get(kind)
        r = Relation(src, kind, dst, int(t_from_ns))
        if self.find(r.key) is not None:  # closed at its own start: valid again from there
            self._swap(r)
            if inv is not None:
                self._swap(Relation(dst, inv, src, int(t_from_ns)))
            return
        self._put(r)
        if inv is not None:
            self._put(Relation(dst, inv, src, int(t_from_ns)))

    def close(self, src: int, kind: RelationKind, dst: int, t_to_ns: int) -> bool:
        """End the open ``src --kind--> dst`` (and its inverse) at ``t_to_ns``; False if none."""
        kind = RelationKind(kind)
        found = self._close_one(src, kind, dst, t_to_ns)
        inv = INVERSE.get(kind)
        if found and inv is not None:
            self._close_one(dst, inv, src, t_to_ns)
        return found

    def restart(self, t_end_ns: int, t_start_ns: int) -> int:
        """A clock that went back (a log whose time restarts): every open part-of and spatial
        relation ends at ``t_end_ns``, the last time of the old clock, and holds again from
        ``t_start_ns`` on the new one, so a later end on the new clock does not precede its
        start (an event's relations, which nothing ends, stay as they are). Returns how many
        relations (each direction counted) were restarted."""
        n = 0
        for rels in self._out.values():
            for r in list(rels):
                if r.kind in ENDED and r.t_to_ns is None and r.t_from_ns <= t_end_ns:
                    self._swap(replace(r, t_to_ns=int(t_end_ns)))
                    self._put(replace(r, t_from_ns=int(t_start_ns)))
                    n += 1
        return n

    def remove_node(self, node: int) -> None:
        """Drop every relation touching ``node`` (used when short-term memory forgets it)."""
        for r in self._out.pop(node, []):
            self._in[r.dst] = [x for x in self._in.get(r.dst, []) if x.src != node]
        for r in self._in.pop(node, []):
            self._out[r.src] = [x for x in self._out.get(r.src, []) if x.dst != node]
        self.dirty = {k for k in self.dirty if node not in (k[0], k[2])}

    def load(self, rels: Iterable[Relation]) -> None:
        """Put stored relations back (both directions are stored, so no inverse is added)."""
        for r in rels:
            self._put(r, dirty=False)

    def _put(self, r: Relation, dirty: bool = True) -> None:
        self._out.setdefault(r.src, []).append(r)
        self._in.setdefault(r.dst, []).append(r)
        if dirty:
            self.dirty.add(r.key)

    def _close_one(self, src: int, kind: RelationKind, dst: int, t_to_ns: int) -> bool:
        for r in self._out.get(src, []):
            if r.kind == kind and r.dst == dst and r.t_to_ns is None:
                if t_to_ns < r.t_from_ns:
                    raise KDError(
                        f"relation {src} {kind.value} {dst}: end t_ns={t_to_ns} is before its "
                        f"start t_ns={r.t_from_ns}"
                    )
                self._swap(replace(r, t_to_ns=int(t_to_ns)))
                return True
        return False

    def _swap(self, new: Relation) -> None:
        """Replace the stored relation with ``new``'s key by ``new``."""
        outs, ins = self._out[new.src], self._in[new.dst]
        i = next(k for k, r in enumerate(outs) if r.key == new.key)
        j = next(k for k, r in enumerate(ins) if r.key == new.key)
        outs[i] = ins[j] = new
        self.dirty.add(new.key)

    def find(self, key: tuple[int, str, int, int]) -> Relation | None:
        for r in self._out.get(key[0], ()):
            if r.key == key:
                return r
        return None


#: Spatial kinds (4.4.2, situational pointers): they link entities only.
SPATIAL = frozenset(
    {K.ON_TOP_OF, K.BENEATH, K.BESIDE, K.IN_FRONT_OF, K.BEHIND, K.INSIDE_OF, K.NEAR}
)
#: The kinds the world model ends as what it observes changes (parts, places); an event's
#: relations are never ended.
ENDED = frozenset({K.BELONGS_TO, K.HAS_PART}) | SPATIAL


class FramePointers:
    """The KD's pointers between frames: a :class:`RelationGraph` plus the checks that need to
    know what each end is.

    ``kind_of(frame_id, where)`` says ``"entity"`` or ``"event"`` (KDError naming ``where``
    for an unknown id); ``now(t_ns)`` is ``t_ns`` or, when None, this cycle's time (else 0).
    Times are int64 nanoseconds."""

    def __init__(
        self,
        graph: RelationGraph,
        kind_of: Callable[[int, str], str],
        now: Callable[[int | None], int],
    ) -> None:
        self.graph = graph
        self._kind_of = kind_of
        self._now = now

    def relate(self, src: int, kind: RelationKind | str, dst: int, t_ns: int | None) -> None:
        """Point ``src --kind--> dst`` from ``t_ns`` on, if both ends may be so linked."""
        kind = _kind(kind, src, dst)
        where = f"relation {src} {kind.value} {dst}"
        ks, kd = self._kind_of(src, where), self._kind_of(dst, where)
        if kind in (K.BELONGS_TO, K.HAS_PART) and ks != kd:
            raise KDError(f"{where}: a {ks} cannot be part of an {kd} (or the other way)")
        if kind in SPATIAL and "event" in (ks, kd):
            raise KDError(
                f"{where}: spatial relations link entities, {src} is a {ks}, {dst} a {kd}"
            )
        if kind == K.INVOLVES and (ks, kd) != ("event", "entity"):
            raise KDError(f"{where}: involves points from an event to an entity, not {ks}->{kd}")
        self.graph.add(src, kind, dst, self._now(t_ns))

    def unrelate(self, src: int, kind: RelationKind | str, dst: int, t_ns: int | None) -> bool:
        """End ``src --kind--> dst`` at ``t_ns`` (kept in history); False if it was not open."""
        return self.graph.close(src, _kind(kind, src, dst), dst, self._now(t_ns))

    def pointers(
        self, frame_id: int, kind: RelationKind | str | None, t_ns: int | None
    ) -> list[int]:
        self._kind_of(frame_id, "pointers")
        return self.graph.out(frame_id, None if kind is None else RelationKind(kind), t_ns)

    def pointed_by(
        self, frame_id: int, kind: RelationKind | str | None, t_ns: int | None
    ) -> list[int]:
        self._kind_of(frame_id, "pointed_by")
        return self.graph.inn(frame_id, None if kind is None else RelationKind(kind), t_ns)

    def relations(self, frame_id: int) -> list[Relation]:
        self._kind_of(frame_id, "relations")
        return self.graph.relations_of(frame_id)

    def parent(self, frame_id: int, t_ns: int | None) -> int | None:
        self._kind_of(frame_id, "parent")
        return self.graph.parent(frame_id, t_ns)

    def parts(self, frame_id: int, t_ns: int | None) -> list[int]:
        return sorted(self.pointers(frame_id, K.HAS_PART, t_ns))

    def ancestors(self, frame_id: int, t_ns: int | None) -> list[int]:
        self._kind_of(frame_id, "ancestors")
        return self.graph.ancestors(frame_id, t_ns)

    def parts_tree(self, frame_id: int, t_ns: int | None) -> list[tuple[int, int]]:
        self._kind_of(frame_id, "parts_tree")
        return self.graph.parts_tree(frame_id, t_ns)

    def neighbourhood(
        self,
        frame_id: int,
        kinds: Iterable[RelationKind | str] | None,
        depth: int,
        t_ns: int | None,
    ) -> dict[int, int]:
        self._kind_of(frame_id, "neighbourhood")
        ks = None if kinds is None else [RelationKind(k) for k in kinds]
        return self.graph.neighbourhood(frame_id, ks, depth, t_ns)

    def involving(self, entity_id: int) -> list[int]:
        """Events with an open ``involves`` pointer to ``entity_id``."""
        self._kind_of(entity_id, "events by participant")
        return self.graph.inn(entity_id, K.INVOLVES)

    def mark_touching(self, nodes: Iterable[int]) -> None:
        """Mark every relation from or into ``nodes`` for writing (they just entered
        long-term memory, so their pointers can be written now)."""
        for node in nodes:
            self.graph.dirty.update(r.key for r in self.graph.relations_of(node))
            self.graph.dirty.update(r.key for r in self.graph.relations_into(node))

    def collect(self, in_ltm: Callable[[int], bool]) -> list[Relation]:
        """The changed relations the next flush writes: both ends in long-term memory."""
        rels = [r for k in self.graph.dirty if (r := self.graph.find(k)) is not None]
        return [r for r in rels if in_ltm(r.src) and in_ltm(r.dst)]


def _kind(kind: RelationKind | str, src: int, dst: int) -> RelationKind:
    try:
        return RelationKind(kind)
    except ValueError:
        raise KDError(f"relation {src} {kind!r} {dst}: unknown relation kind") from None
