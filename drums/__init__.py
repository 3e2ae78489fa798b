"""Drums: middleware-aware monitoring for distributed robots."""
