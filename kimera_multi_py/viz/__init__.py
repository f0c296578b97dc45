"""Visualisation sinks (Rerun), with a null object when visualisation is off."""
