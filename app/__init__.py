"""``drivingscene-view``: the desktop viewer and editor of DrivingScene reconstructions.

Layout (the data path reads top to bottom): ``loader`` turns a file into a ``Reconstruction`` in a
background thread; ``state`` holds the open scene, the time, the selection and every edit (with
undo); ``camera`` turns navigation into ``world_to_cam`` + intrinsics in the library's conventions;
``sorter`` orders splats by depth off the UI thread; ``renderer`` draws them with the shaders in
``shaders/``; ``window`` routes input (imgui first) and runs the frame loop; ``panels`` are the UI;
``export`` and ``headless`` write files. The app imports the library, never ``drivingscene.train``.
"""
