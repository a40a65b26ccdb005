"""Instrument drivers (bytes on wires) and the simulated devices that speak the same bytes.

``drivers`` knows nothing about scans or maps.
"""
