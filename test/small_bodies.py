"""Small bodies several test files build scenes from."""


def star3(model, **scene):
    """A small voxel star, a hub and three arms, its hub's bottom clamped (auto domains:
    core + 3 limbs). model: the scene's model section; scene: more top-level keys."""
    return dict({"name": "star3", "body": {
        "mesh": {"generator": "voxels", "cell": 0.03, "primitives": [
            {"shape": "cylinder", "radius": 0.06, "height": 0.12, "position": [0, 0, 0.06]},
            {"shape": "box", "size": [0.33, 0.06, 0.06], "position": [0.2, 0, 0.09]},
            {"shape": "box", "size": [0.06, 0.33, 0.06], "position": [0, 0.2, 0.09]},
            {"shape": "box", "size": [0.33, 0.06, 0.06], "position": [-0.2, 0, 0.09]}]},
        "material": {"model": "neohookean", "young": 1e6, "poisson": 0.3, "density": 1000}},
        "pins": [{"plane": {"point": [0, 0, 0.01], "normal": [0, 0, -1]}}],
        "model": model}, **scene)
