"""The built-in datasets (`mvtex synth`): garments with pose-driven folds and fitted inferred meshes.
"""
