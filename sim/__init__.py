"""tacsplat.sim (see DESIGN.md)."""
