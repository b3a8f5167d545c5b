"""tacsplat.datasets (see DESIGN.md)."""
