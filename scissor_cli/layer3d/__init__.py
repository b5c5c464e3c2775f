"""The 3-D slab that tests the layer assumption (docs/model.md §13).

* `extrude`: the layer's triangles extruded into graded prism layers, three tetrahedra each.
* `slab`: the slab as a 3-D `mechanics.Tissue` (boundary, material), and points of the layer on it.
* `check`: the layer check of a forward case: slab against the 2-D layer, plane strain against plane stress.
* `truth`: the slab as the closed loop's true tissue (`trials.truth: slab`).
"""
