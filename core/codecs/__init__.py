"""Sans-io codecs for every wire format and file the sources speak.

Each module turns bytes into events and events into bytes and does nothing
else: no sockets, no serial ports, no clock. Streaming decoders take bytes in
any chunking through ``feed(data) -> list[event]`` and give the same events
whatever the chunking; ``close()`` reports what is left at the end of input.

| module          | wire format                                                   |
|-----------------|---------------------------------------------------------------|
| smartsuit_can   | SmartSuit CAN frames (000 seed, ch. 3), and slcan text lines  |
| concentrator    | Data Concentrator serial exchange (000 seed, ch. 3.4.2, 4.1)  |
| imu_matrix      | IMU central "data matrix" lines (003 seed, ch. 7.5.3, App. A) |
| slimevr         | SlimeVR trackers' UDP protocol, the server's side (and the    |
|                 | tracker's, for the emulated tracker)                          |
| orientation     | OpenSense quaternion ``.sto`` and per-segment quaternion CSV  |
| raw_sample      | bodynet's raw-sample message carried on Zenoh                 |
"""
