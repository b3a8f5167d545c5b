"""tacsplat.acquisition (see DESIGN.md)."""
