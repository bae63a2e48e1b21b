"""recording: see DEVELOPING.md."""
