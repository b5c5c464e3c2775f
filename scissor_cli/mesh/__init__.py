"""Quality triangle meshes of the layer and points carried by them (docs/model.md §2, §9)."""
