"""How the target is seen: the sensors the closed loop reads (docs/model.md §8, §17)."""
