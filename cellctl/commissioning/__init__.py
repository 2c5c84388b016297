"""Taking a cell from wired to scanning: `cellctl doctor` (is this PC ready for the real cell) and the
hand-eye calibration. Imports nothing from cellctl.service nor cellctl.bench (tests/test_rooms.py)."""
