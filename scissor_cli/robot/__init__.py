"""The puncture module: DH kinematics, inverse kinematics and the workspace (docs/model.md §11)."""
