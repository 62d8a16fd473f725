"""OpenCL C / CUDA C kernel sources of NebulaRT, shipped as package data.

The sources are data: the library's backends read them with
:func:`importlib.resources.files` and compile them at run time.
"""
