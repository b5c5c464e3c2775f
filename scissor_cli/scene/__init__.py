"""The scene: the tissue layer, cups, targets, obstacles and the camera, as plain data (docs/model.md §1, §8)."""
