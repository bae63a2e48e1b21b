"""Reports: plots (matplotlib), CSV and markdown written from core results; the only place besides cli/ that draws."""
