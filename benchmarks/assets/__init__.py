"""Baking and exporting: cost against mesh and texture size, xatlas's charts, kept UV layouts,
welded exports and levels of detail."""
