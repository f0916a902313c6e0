"""Vehicle: what the bridge knows about each vehicle it serves. Its IMU samples and their
board clock (ingest, clock), the streams asked of it (negotiate), its declination,
velocity aiding, kind (model) and the references of the live comparison as they arrive,
all kept per vehicle (vehicle.py). May import ``wire``."""
