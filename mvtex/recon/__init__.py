"""Multi-view reconstruction of the gt geometry from texcoord sets (`mvtex triangulate`).
"""
