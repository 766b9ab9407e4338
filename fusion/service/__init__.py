"""The armfusion service over Eclipse Zenoh: key expressions, payloads, and the nodes.

See docs/service.md. Every session is configured by :mod:`armfusion.fusion.service.zenoh_config`:
loopback only, no scouting.
"""
