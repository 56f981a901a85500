"""A job handler that renders through EGL and then loads the model libraries (with a CUDA build of torch,
``torch._dynamo`` pulls in triton, which must not be imported after Mesa's EGL is up)."""


def run(ctx):
    from studio.sim.env import SimEnv

    with SimEnv("pick_place", "panda", image_size=(60, 80)) as env:
        env.reset("pick_place/cube->red", 0)
        mean = float(env.render().mean())
    import torch._dynamo

    from studio.model.osvi_wm import OSVIWM  # noqa: F401

    return {"mean": mean, "torch": str(torch.__version__)}
