"""Fitting stage: body fits to point clouds, chair registration, contacts, `couch-process`.
Filled in by the fitting and chair-registration issues."""
