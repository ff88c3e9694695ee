"""Rolling multiresolution maps (one geometry per level, many named layers) and shared geometry.

Modules (imported one by one: this package stays import-light so ``core.geometry`` is cheap):

* ``maps.level``: one rolling level (toroidal layers, world <-> cell <-> storage indices);
  ``maps.layers`` the layer table; ``maps.submap`` box / circle / polygon / line selections.
* ``maps.stack``: levels 2-5 scrolling together; ``MapStack.fuse`` feeds world points.
* ``maps.fusion``: per-cell Kalman height, moments, occupancy, labels from SP entity images.
* ``maps.terrain``: slope, step height, traversability.
* ``maps.apriori``: a priori elevation rasters (Argoverse 2 ground height) into coarse levels.
* ``maps.registration``: local map vs a priori / earlier map by pyramid correlation.
* ``maps.tiles``: long-term memory of tiles leaving the window.
* ``maps.pictures``: PNG pictures of layers and of all levels side by side.
* ``core.geometry`` (shared geometry) and ``maps.pyramid`` (pyramids of scale, correlation).
"""
