"""Sub-commands of run-cell, one module per family."""
