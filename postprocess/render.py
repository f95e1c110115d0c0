#!/usr/bin/env python
"""Render a run off-screen: the same as `vesflow render`.

    python postprocess/render.py out/run.h5 -o out/run.mp4 --frames out/run_frames --color tension
    python postprocess/render.py out/vtk/run.pvd --color speed --no-movie --frames out/png

Headless machines: VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow (set automatically
when DISPLAY is unset).  Options: --size 960x540, --fps, --clim LO HI, --view AZ EL.
"""
import sys

from vesflow.render import main

if __name__ == "__main__":
    sys.exit(main(prog="postprocess/render.py"))
