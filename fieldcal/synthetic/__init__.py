"""Exact synthetic sessions: field geometries, the image renderer, goniometer sessions.
"""
