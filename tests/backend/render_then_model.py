"""A job handler that renders through EGL and then loads the model libraries (torchvision pulls in triton)."""


def run(ctx):
    from studio.sim.env import SimEnv

    with SimEnv("pick_place", "panda", image_size=(60, 80)) as env:
        env.reset("pick_place/cube->red", 0)
        mean = float(env.render().mean())
    import torchvision

    return {"mean": mean, "torchvision": str(torchvision.__version__)}
