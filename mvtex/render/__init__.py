"""Rendering with moderngl (headless EGL): rasterization into triangle ids, textured pictures.
"""
