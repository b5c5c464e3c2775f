"""Ultrasound imaging of the layer: probe, scatterers, image formation and speckle tracking (docs/model.md §17)."""
