"""fusion: see DEVELOPING.md."""
