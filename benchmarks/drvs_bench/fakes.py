"""The fake cameras are drvs.tools.fakes (the tests use them too); their names stay importable here."""

from drvs.tools.fakes import AckingCamera as AckingCamera
from drvs.tools.fakes import register_message as register_message
from drvs.tools.fakes import serve_camera as serve_camera
