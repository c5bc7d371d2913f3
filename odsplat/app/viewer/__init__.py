"""`odsplat view CAPTURE`: the reconstruction's Gaussians, magnified in 3D at render time, with the modes, the FRFs
and the measured signals linked to them. `model` is the Qt-free core (what a capture has, the view's state, the
one renderer); `load` reads a capture into it; `draw` draws over the rendered view; `export` writes videos and
screenshots through it; `app` is the PySide6 + pyqtgraph window."""
from odsplat.app.viewer.export import export_video, save_screenshot
from odsplat.app.viewer.load import load_viewer
from odsplat.app.viewer.model import (
    Mode,
    Orbit,
    Scene,
    SensorInfo,
    ViewerData,
    ViewState,
    default_state,
    render_view,
)

__all__ = ["Mode", "Orbit", "Scene", "SensorInfo", "ViewState", "ViewerData", "default_state", "export_video",
           "load_viewer", "render_view", "save_screenshot"]
