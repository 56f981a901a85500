# OSVI Studio in a container: the same installer and entry point as the README's two commands.
#   docker build -t osvi-studio .
#   docker run -p 8080:8080 osvi-studio            # the studio, bound to all interfaces inside the container
FROM python:3.11-slim-bookworm
ENV DEBIAN_FRONTEND=noninteractive MUJOCO_GL=egl PYOPENGL_PLATFORM=egl PYTHON=python3.11
WORKDIR /opt/osvi-studio
COPY . .
# scripts/install.sh installs the EGL/Mesa libraries and Chromium, then the Python environment in .venv.
RUN bash scripts/install.sh && rm -rf /var/lib/apt/lists/* /root/.cache/pip
EXPOSE 8080
CMD ["./run", "serve", "--host", "0.0.0.0", "--port", "8080"]
