"""The Zenoh job service: the API models, the job store, the server and its worker, the client, the
yard's router, and a loopback harness (a real `cellctl serve`) for the tests and the load bench. Runs
its jobs through cellctl.scan; imports nothing from cellctl.bench nor cellctl.commissioning
(tests/test_rooms.py)."""
