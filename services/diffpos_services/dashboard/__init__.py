"""dashboard: see DEVELOPING.md."""
