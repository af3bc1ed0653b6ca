"""mfvs services: thin zenoh adapters around plain, importable algorithms."""
import os

# Services render headless (EGL; Mesa's llvmpipe without a GPU). Set MUJOCO_GL yourself to use another backend.
os.environ.setdefault("MUJOCO_GL", "egl")
