"""Geometry without a finite-element space: surfaces and closest points, smoothing,
surface matching, output tessellation, smooth random fields."""
