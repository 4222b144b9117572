"""Synthetic fleet: a procedural labelled world, vehicles driving through it, and the submaps
(meshes + meta) they would upload, with the ground truth kept apart."""
