"""What a 3-D scene's run leaves behind: its results.h5 groups and figures (docs/contract.md, "3-D scenes")."""
