"""Simulated missions flown through the core and scored against the renderer's truth."""
