"""Plug-ins: the common calibrator interface, registries by name / entry point / import path, and
the fR methods behind that interface."""
