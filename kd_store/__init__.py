"""The knowledge database: entity and event frames, pointers, classes, memory tiers, persistence.

Reference 001, section 4.4. Start with :func:`open`::

    import kd_store
    with kd_store.open("run.kd") as kd:
        tree = kd.add_entity("tree-1", kd_store.Level.OBJECT, generic_classes=("tree",))
        kd.observe(tree.id, kd_store.make_state(t_ns, "world", (10.0, 2.0, 0.0)))
        kd.sql("SELECT class_name, count(*) FROM entities GROUP BY ALL")
"""

from kd_store.classes import ClassKind, ClassLibrary, ClassPrototype, Discriminant
from kd_store.config import KDConfig, MemoryConfig, PromotionRule
from kd_store.errors import KDError, ResultTooLarge
from kd_store.frames import (
    Attribute,
    EntityFrame,
    EventFrame,
    Level,
    State,
    Status,
    Value,
    make_state,
)
from kd_store.persist import SCHEMA_VERSION
from kd_store.relations import Relation, RelationKind
from kd_store.spatial import Box, Circle
from kd_store.states import StateBatch
from kd_store.store import KnowledgeDatabase, SQLReader, open

__all__ = [
    "SCHEMA_VERSION",
    "Attribute",
    "Box",
    "Circle",
    "ClassKind",
    "ClassLibrary",
    "ClassPrototype",
    "Discriminant",
    "EntityFrame",
    "EventFrame",
    "KDConfig",
    "KDError",
    "KnowledgeDatabase",
    "Level",
    "MemoryConfig",
    "PromotionRule",
    "Relation",
    "RelationKind",
    "ResultTooLarge",
    "SQLReader",
    "State",
    "StateBatch",
    "Status",
    "Value",
    "make_state",
    "open",
]
