"""bus: see DEVELOPING.md."""
