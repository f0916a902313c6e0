"""attitude-bridge service: MAVLink in, estimators, MAVLink/MQTT out, live comparison."""
