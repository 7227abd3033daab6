"""Clients of the body network: viewer, recorder, replay, export, game, report."""
