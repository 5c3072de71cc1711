"""The data mvtex works on: cameras and rigs, meshes, datasets, texcoord sets.
"""
