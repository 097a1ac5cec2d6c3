"""Reading and writing files: frame sources (folders, MCAP), meshes, template libraries, manifests, BOP CSV."""
