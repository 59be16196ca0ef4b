"""Layer 1, pure core: networks, losses, metrics, ROI geometry, the synthetic renderer.

Imports nothing else from vtgen and touches no files: everything here works on arrays and
tensors, so it is unit-testable in milliseconds (checked by import-linter, see pyproject.toml).
"""
