"""The real-robot bridge's support code (franka.py): libfranka's state and backends, and the workers that run RME's
estimates beside the 1 kHz loop."""
