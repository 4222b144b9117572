"""Clients of the HTTP API: the simulated fleet behind ``fleetmap demo``."""
