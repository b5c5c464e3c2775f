"""What a run leaves behind: results.h5, figures, reports and exports (docs/contract.md)."""
