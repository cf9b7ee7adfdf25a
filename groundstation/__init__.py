"""The ground-station CLI (``pmon gcs`` / ``pmon-gcs``): status, watch, commands and parameters of
the onboard app over MAVLink. Contract: docs/MAVLINK.md; operating: docs/OPERATING.md."""
