# OSVI Studio in a container: the same installer and entry point as the README's two commands.
#   docker build -t osvi-studio .
#   docker run -p 8080:8080 osvi-studio            # the studio, bound to all interfaces inside the container
# The image is the runtime only: no test extras (pytest, playwright, ruff, mypy, ...) and no Chromium; the
# tests run outside it with `./run test`. What goes into the build context is set by .dockerignore.
FROM python:3.11-slim-bookworm
# STUDIO_EXTRAS="" and STUDIO_BROWSER=0 select the runtime install (see scripts/install.sh). They stay set in
# the image, so the installer that `./run serve` calls at start finds the environment complete.
ENV DEBIAN_FRONTEND=noninteractive MUJOCO_GL=egl PYOPENGL_PLATFORM=egl PYTHON=python3.11 \
    STUDIO_EXTRAS="" STUDIO_BROWSER=0
WORKDIR /opt/osvi-studio

# 1. Dependencies, in a layer that is rebuilt only when pyproject.toml or the installer change: copy just
#    those, plus an empty package (and README, which pyproject names) so that pip can install the project
#    in editable mode; the real files replace them below.
COPY pyproject.toml ./
COPY scripts/install.sh scripts/
RUN mkdir -p studio && touch studio/__init__.py README.md \
    && bash scripts/install.sh \
    && rm -rf /var/lib/apt/lists/* /root/.cache/pip

# 2. The source (a code change rebuilds from here on only).
COPY . .
EXPOSE 8080
CMD ["./run", "serve", "--host", "0.0.0.0", "--port", "8080"]
