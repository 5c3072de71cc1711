"""Texture sliding (DESIGN §5): per (pose, camera) texcoords that show the gt material.
"""
