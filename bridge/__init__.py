"""attitude-bridge service: MAVLink in, estimators, MAVLink/MQTT out, live comparison.

Wings, data flowing one way: ``wire`` (bytes <-> messages) -> ``vehicle`` (per-vehicle
state) -> ``estimate`` (estimators, live comparison) -> ``publish`` (MAVLink, MQTT,
recording), with ``app`` (service, settings, command line) on top. docs/architecture.md
draws it."""
