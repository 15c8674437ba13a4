"""Mitsuba 3: choosing the variant this machine runs, writing and editing scene
XML, the material models with their parameters and bounds, and the numerical
stability probe of those models."""
