"""The tests: `python -m pytest -q` from the repository's folder; helpers.py holds what several of them share."""
