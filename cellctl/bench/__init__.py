"""The benchmarks behind `cellctl bench`: scans in the twin and their report, the job API's latency and
load on loopback, G-NBV's candidate scoring and the all-knowing oracle. May import every other room;
nothing in cellctl/ but cellctl/cli.py imports it (tests/test_rooms.py)."""
