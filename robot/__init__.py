"""The real-robot bridge's support code (franka.py is its command line): libfranka's state and backends, the 1 kHz
loop with its safety stage, and the workers that run RME's estimates beside it."""
