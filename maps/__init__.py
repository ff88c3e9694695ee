"""Rolling multiresolution maps (one geometry per level, many named layers) and shared geometry."""
