"""The suite runs on PoCL's CPU device unless HLBVH_CL_DEVICE says otherwise."""
import os

os.environ.setdefault("HLBVH_CL_DEVICE", "pocl")
