"""diffpos services: the CLI, bus services (Zenoh), recordings (MCAP), dashboards (Rerun)."""
