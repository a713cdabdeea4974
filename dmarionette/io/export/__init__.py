"""Motion export: the puppet's body motion to BVH and glTF.
"""
