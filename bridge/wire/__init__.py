"""Wire: bytes <-> MAVLink messages. The links (UDP, TCP, serial) and their peers, the
codec (MAVLink 2, signing), fast framing and the in-kernel prefilter, the admission of
senders, packet sequences. Imports nothing else of the bridge: every other wing builds
on it. A new link type: a subclass of ``link.Link`` in a module of its own (like
``udp.py``, ``stream.py``), picked for its URL by ``links.open_link``."""
