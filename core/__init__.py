"""The bottom of the stack: what every other package may import and that imports none of
them (docs/architecture.md)."""
