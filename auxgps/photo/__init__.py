"""Landmark maps from geotagged photos, and photos located against them alone.

- :mod:`auxgps.photo.types`: the records shared by mapping and locating (:class:`~auxgps.photo.types.PhotoPrior`,
  :class:`~auxgps.photo.types.MapPhoto`, :class:`~auxgps.photo.types.PhotoMap`, :class:`~auxgps.photo.types.PhotoFix`,
  ...) and the camera-attitude helpers.
- :mod:`auxgps.photo.features`: SIFT features and descriptor matching between two photos.
- :mod:`auxgps.photo.tracks`: matches chained into tracks; the first guess of poses and points.
- :mod:`auxgps.photo.bundle`: the bundle adjustment and the refinement of points alone.
- :mod:`auxgps.photo.build`: :func:`~auxgps.photo.build.build_photo_map`, the mapping pipeline.
- :mod:`auxgps.photo.locate`: :class:`~auxgps.photo.locate.PhotoLocator`, a photo located against a map.

Frames: local NED (m) about the map's origin; camera frame OpenCV (x right, y down, z forward); ``R_ned_cam``
maps camera into NED. Pixels are full-resolution pixels of the stored photo.

Pure core: arrays and dataclasses in, dataclasses out; files are read and written in :mod:`auxgps.io` and
:mod:`auxgps.photo_workflow`.
"""
