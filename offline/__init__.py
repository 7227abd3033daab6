"""Offline processing: a capture or file through the gateway's solver into MCAP.

This role sits above ``nodes`` (whose sources read the files), ``gateway``
(whose solver it runs) and ``clients`` (whose MCAP store it writes), like the
command line; nothing below it imports it.
"""
