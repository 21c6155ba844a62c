"""ns-recolor: palette and hue recoloring of any Nerfstudio NeRF run, and the color-branch fine-tune attack."""
