"""Helpers a change is checked with."""
