"""The payload's inertia from motion: Savitzky-Golay derivatives, a physically consistent 10-parameter fit and the
inertial compensation that wraps RME (motion/inertia.py, motion/compensation.py; docs/inertia.md)."""
