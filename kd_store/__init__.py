"""The knowledge database: entity and event frames, pointers, classes, memory tiers, persistence."""
