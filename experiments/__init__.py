"""User commands: ``python -m experiments.run <problem>``, ``python -m experiments.guidance_study``."""
