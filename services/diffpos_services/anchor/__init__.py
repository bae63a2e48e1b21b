"""anchor: see DEVELOPING.md."""
