"""numpy images as GL textures for imgui (``imgui.image(ImTextureRef(tex.glo), size)``), cached by key."""

from __future__ import annotations

import numpy as np


class TextureCache:
    def __init__(self, ctx):
        self.ctx = ctx
        self._textures: dict[str, object] = {}

    def get(self, key: str, image_fn) -> object:
        """The texture for ``key``, creating it from ``image_fn()`` (uint8 ``[H, W, 3]``) the first time."""
        tex = self._textures.get(key)
        if tex is None:
            image = np.ascontiguousarray(image_fn(), np.uint8)
            tex = self.ctx.texture((image.shape[1], image.shape[0]), 3, image.tobytes())
            tex.filter = (self.ctx.LINEAR, self.ctx.LINEAR)
            self._textures[key] = tex
        return tex

    def clear(self) -> None:
        for tex in self._textures.values():
            tex.release()
        self._textures.clear()


def texture_ref(tex):
    from imgui_bundle import imgui

    return imgui.ImTextureRef(tex.glo)
