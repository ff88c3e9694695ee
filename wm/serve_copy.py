"""What the live node copies at the end of each cycle for the server's answers beyond the
entity columns and What If (:class:`wm.serve.CycleSnapshot`), and how it chooses.

The map levels are written in place (fusion, the terrain and cost layers, the toroidal
scrolling that clears the cells leaving a window: ``maps.level``, ``maps.stack``), so a
reference to a level's array would change under a reader: only a copy stays as the cycle left
it. Copying every layer of every level each cycle costs too much: at the default geometry (4
levels of 256 x 256 cells, 19 layers, 96 bytes a cell) the stack holds 24 MB (a finer or larger
configuration 64 MB and more), whose copy took 2.5 ms on the 2-core development host with its
pages warm and 14 ms with it loaded by other jobs (fresh pages, about 1.7 GB/s), against a node
cycle of about 40 ms of CPU: up to a third of the cycle, where the budget is a tenth. So the
copy holds, per level:

* the four layers What If samples (:data:`wm.whatif.SAMPLED_LAYERS`) of the levels it serves:
  copied every cycle for What If and IsPathValid already (4 MB at the default geometry; the
  whole copy with nothing else asked took 0.4-0.6 ms after a replay of the default scenario),
  they also answer map windows, GetGridMap and CheckSafety;
* the layers clients asked for in the last :data:`DEMAND_TTL_S` seconds (:class:`ServedDemand`;
  a float32 layer of a 256 x 256 level is 256 kB, a float64 or int64 one 512 kB), most recently
  asked first while their bytes stay within :data:`MAX_ASKED_LAYER_BYTES` (4 MiB: +0.3-0.6 ms
  measured so, about 2.4 ms at the loaded rate; nothing when nobody asks).

A window of a layer the copy does not hold (the first request for it, or one beyond the byte
limit) is read under the node's lock from the node's own level, copying only the window's cells,
as before the copy existed; the request registers the layer, so the cycles after copy it. Events
and the entities of attention are copied on the same terms (their cost grows with the events in
RAM and the entities of the level, nothing when nobody asks; measured: 69 event frames,
references only, under 0.1 ms; level 4's attention, 13 entities of 82, 0.3-0.4 ms). The class
taxonomy a class filter needs is copied whenever the class library changed (a specific class
founded), else shared with the cycle before. ``/v1/status`` gives the copy's wall time per cycle
(``snapshot_ms``) and its map bytes (``snapshot_map_bytes``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Hashable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from kd_store.classes import descendants
from kd_store.errors import KDError

#: wall seconds a view stays in the per-cycle copy after a client last asked for it
DEMAND_TTL_S = 30.0
#: bytes of map layers asked for (beyond What If's) the node copies per cycle at most
MAX_ASKED_LAYER_BYTES = 4 * 2**20

EVENTS: tuple[str] = ("events",)  # the demand key of the KD's event frames


def layer_key(level: str, layer: str) -> tuple[str, str, str]:
    """The demand key of one layer of one map level."""
    return ("layer", level, layer)


def attention_key(sp_level: int) -> tuple[str, int]:
    """The demand key of the entities of attention of one SP level (1..5)."""
    return ("attention", int(sp_level))


class ServedDemand:
    """Which views clients asked for lately: each key with the time (monotonic s) it was last
    asked. Requests call :meth:`ask` in the server's threads; the node's thread reads
    :meth:`wanted` at the end of each cycle."""

    def __init__(self, ttl_s: float = DEMAND_TTL_S, clock: Callable[[], float] = time.monotonic):
        self.ttl_s, self._clock = ttl_s, clock
        self._asked: dict[Hashable, float] = {}
        self._lock = threading.Lock()  # the server's threads and the node's: held for a dict op
        # called (outside the lock) when a key not held is asked for: a node in another
        # process is told at once, so that its next cycle copies it (wm.serve_proc)
        self.on_new: Callable[[], None] | None = None

    def ask(self, keys: Iterable[Hashable]) -> None:
        """Note that ``keys`` were asked for now."""
        now = self._clock()
        new = False
        with self._lock:
            for k in keys:
                last = self._asked.pop(k, None)  # an expired key not yet forgotten is new
                new |= last is None or last < now - self.ttl_s
                self._asked[k] = now  # re-inserted last: the dict is in order of asking
        if new and self.on_new is not None:
            self.on_new()

    def wanted(self) -> list[Hashable]:
        """The keys asked for within the last ``ttl_s`` seconds, most recently asked first;
        older ones are forgotten."""
        cutoff = self._clock() - self.ttl_s
        with self._lock:
            for k in [k for k, t in self._asked.items() if t < cutoff]:
                del self._asked[k]
            return list(reversed(self._asked))


def layer_bytes(level: Any, layer: str) -> int:
    """Bytes of one layer of ``level`` (a :class:`maps.level.MapLevel`)."""
    spec = next(s for s in level.config.layers if s.name == layer)
    return level.size * level.size * np.dtype(spec.dtype).itemsize


def layers_to_copy(
    stack: Any, sampled: Iterable[str], wanted: list[Hashable], budget_bytes: int
) -> dict[str, tuple[str, ...]]:
    """Per level of ``stack``, the layers the cycle's copy holds: What If's
    :data:`~wm.whatif.SAMPLED_LAYERS` for the levels in ``sampled``, then the layers among
    ``wanted`` (demand keys, most recently asked first) while their bytes stay within
    ``budget_bytes``. A level with none maps to ``()`` (its geometry is copied all the same)."""
    from wm.whatif import SAMPLED_LAYERS

    sampled = set(sampled)
    out = {lvl.name: list(SAMPLED_LAYERS) if lvl.name in sampled else [] for lvl in stack.levels}
    by_name = {lvl.name: lvl for lvl in stack.levels}
    spent = 0
    for key in wanted:
        if not (isinstance(key, tuple) and key[0] == "layer"):
            continue
        _, level, layer = key
        lvl = by_name.get(level)
        if lvl is None or layer in out[level] or layer not in lvl.specs:
            continue
        size = layer_bytes(lvl, layer)
        if spent + size > budget_bytes:
            continue  # a smaller one further down may still fit
        spent += size
        out[level].append(layer)
    return {name: tuple(layers) for name, layers in out.items()}


def copy_levels(stack: Any, layers: dict[str, tuple[str, ...]]) -> Any:
    """:class:`~wm.whatif.StackCopy` of every level of ``stack`` holding ``layers[name]``
    (:func:`layers_to_copy`); call it where nothing writes the stack."""
    from wm.whatif import LevelCopy, StackCopy

    return StackCopy([LevelCopy(lvl, layers.get(lvl.name, ())) for lvl in stack.levels])


def map_bytes(stack_copy: Any | None) -> int:
    """Bytes of the map layers a :class:`~wm.whatif.StackCopy` holds (0 for None)."""
    return 0 if stack_copy is None else sum(lvl.nbytes for lvl in stack_copy.levels)


@dataclass(frozen=True)
class Taxonomy:
    """The class library's ``is_a`` links as one cycle left them (``is_a[name]``: the parent,
    None for a root), for class filters answered without the node's lock. ``library`` and
    ``version`` say which library state it copies (:meth:`of` reuses an unchanged one)."""

    is_a: dict[str, str | None]
    library: Any
    version: int

    @classmethod
    def of(cls, library: Any, previous: Taxonomy | None = None) -> Taxonomy:
        """The taxonomy of ``library`` (a :class:`kd_store.ClassLibrary`): ``previous`` when it
        copies the same library unchanged since, else a new copy (O(classes))."""
        version = int(library.version)
        if previous is not None and previous.library is library and previous.version == version:
            return previous
        return cls({p.name: p.is_a for p in library}, library, version)

    def __reduce__(self) -> tuple:
        # sent to the server's process without the class library (the node's KD holds it):
        # the links and the version are what a class filter reads
        return (Taxonomy, (self.is_a, None, self.version))

    def descendants(self, name: str) -> set[str]:
        """``name`` and every class whose lineage contains it, as
        :meth:`kd_store.ClassLibrary.descendants` (the same error for an unknown class)."""
        if name not in self.is_a:
            raise KDError(f"class {name!r} is not in the class library")
        return descendants(self.is_a, name)
