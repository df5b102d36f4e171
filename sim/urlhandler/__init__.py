"""pyserial URL handlers of the simulator, registered through the `erni.serial_handlers` entry point.

`simrobot://` opens a simulated ARCOS robot in the calling process (see `protocol_simrobot`).
The motion plugin knows nothing of the simulator: it opens any pyserial URL, and pyserial
finds this package among its `protocol_handler_packages`.
"""
