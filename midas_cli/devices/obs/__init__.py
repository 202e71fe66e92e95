"""OBS Studio as the video device: recording controlled over obs-websocket v5 (``obs://HOST:PORT``).

``device`` is the backend, ``connection`` wraps obsws-python (authentication, typed errors, record
events stamped with host time), ``profile`` points OBS's recording at the session, and ``frames``
holds the pure frame-clock arithmetic and the check of the finished file.
"""
