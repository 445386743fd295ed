"""Add-on preferences: local model weights, and PyTorch (found, or installed on request)."""

import bpy

from ..operators import ADDON_PACKAGE, dependencies
from ..operators.tasks import JobState


def draw_dependencies(layout, index_url: str = "") -> None:
    """PyTorch status with the install button, its progress and Cancel, or how the last install ended (preferences
    and the main panel)."""
    installer = dependencies.Installer.current()
    box = layout.box()
    if dependencies.torch_available():
        box.label(text="PyTorch is available", icon="CHECKMARK")
        return
    if installer is not None and installer.running:
        box.label(text=f"Installing {dependencies.TORCH_REQUIREMENT}...", icon="SORTTIME")
        box.label(text=installer.text[-90:])
        box.operator("dresg.cancel_install", icon="CANCEL")
        return
    if installer is not None and installer.state is JobState.ERROR:
        column = box.column(align=True)
        column.alert = True
        column.label(text="Installing PyTorch failed:", icon="ERROR")
        for line in installer.lines[-4:]:
            column.label(text=line[-90:])
    elif installer is not None and installer.state is JobState.CANCELLED:
        box.label(text=installer.text, icon="CANCEL")
    else:
        box.label(text="Stylizing needs PyTorch (import, export and viewing do not)", icon="INFO")
    operator = box.operator("dresg.install_dependencies", icon="IMPORT")
    operator.index_url = index_url
    box.label(text=f"{dependencies.TORCH_REQUIREMENT} goes to {dependencies.site_packages_dir()}")


class DRESG_AddonPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_PACKAGE

    sd15_path: bpy.props.StringProperty(
        name="Stable Diffusion 1.5",
        description="A diffusers folder (unet/, vae/, text_encoder/) or a single .safetensors checkpoint",
        subtype="FILE_PATH",
    )
    dino_path: bpy.props.StringProperty(
        name="DINOv2",
        description="Local DINOv2 weights for the feature loss (empty: weight-free patch features)",
        subtype="FILE_PATH",
    )
    index_url: bpy.props.StringProperty(
        name="Package Index",
        description="Where Install Dependencies downloads PyTorch from (empty: PyPI), "
        "e.g. https://download.pytorch.org/whl/cpu for a smaller CPU-only build",
    )

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        column = layout.column(heading="Models")
        column.prop(self, "sd15_path")
        column.prop(self, "dino_path")
        layout.separator()
        layout.prop(self, "index_url")
        draw_dependencies(layout, self.index_url)


classes = (DRESG_AddonPreferences,)
