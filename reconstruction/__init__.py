"""tacsplat.reconstruction (see DESIGN.md)."""
