"""The scan-drawing job: the devices of the cell's mode (twin, fcisim, real), the scan loop, the cutting
path, run folders, plots and Rerun recordings; no network. Imports nothing from cellctl.service,
cellctl.bench or cellctl.commissioning, nor zenoh (tests/test_rooms.py)."""
