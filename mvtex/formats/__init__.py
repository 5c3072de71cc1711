"""File formats at the boundary: COLMAP models, PLY and GLB meshes.
"""
