"""The operator's tablet: a web app (NiceGUI) that is a Zenoh client of the job API like any other.

It reads and commands cells only through `cellctl.service.client` and the API models, so it holds no
privileged path into a cell. It must not import scan, bench or commissioning (tests/test_rooms.py)."""
