"""Makes this Python's OpenCV one without some of its modules, as an OpenCV build without contrib
(opencv-python-headless installed over opencv-contrib-python-headless) is: put this folder first on
PYTHONPATH and name the attributes in DRVS_TEST_CV2_WITHOUT (comma-separated, e.g.
"HOGDescriptor,aruco"). Python imports `sitecustomize` at start; this one imports the real cv2 and
deletes those attributes from it, and makes `import cv2.<name>` fail, so every later `import cv2`
gets the same real OpenCV minus them. Nothing else of cv2 changes."""

import os
import sys

_WITHOUT = [name for name in os.environ.get("DRVS_TEST_CV2_WITHOUT", "").split(",") if name]
if _WITHOUT:
    import cv2

    for _name in _WITHOUT:
        if hasattr(cv2, _name):
            delattr(cv2, _name)
        sys.modules[f"cv2.{_name}"] = None  # type: ignore[assignment]  # `import cv2.aruco` raises ImportError
