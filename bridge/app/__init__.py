"""App: the service that wires the other wings together (service), its settings (config),
the command line (cli, run_cli, calibrate_cli, warmup, health), the live table and the
built-in emulator. Sits on top: may import every wing; no wing imports it."""
