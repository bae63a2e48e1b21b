"""wire: see DEVELOPING.md."""
