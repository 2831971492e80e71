"""Ground Speed Optical Estimator (GSOE): the pure optical part of the navigation module.

Nothing in this package does I/O, plotting or networking; it takes arrays and timestamped samples and returns
estimates. Cameras, MAVLink, files and command lines live in :mod:`nav` and :mod:`sim`.

Conventions (written once here and followed by :mod:`fusion`, :mod:`sim` and :mod:`nav`)
-----------------------------------------------------------------------------------------
Frames
    ``n``  world, local NED: x north, y east, z down, origin at the mission's reference point (flat earth).
    ``b``  body, FRD: x forward (nose), y right wing, z down.  Attitude is the 3-2-1 Euler sequence
           (yaw ``psi`` about z, pitch ``theta`` about y, roll ``phi`` about x) taking ``n`` to ``b``.
    ``c``  raw camera, OpenCV convention: z along the optical axis (out of the lens), x to the right of the
           image (increasing column), y to the bottom of the image (increasing row).  The belly camera's
           nominal mounting is z_c = z_b (looking down), x_c = y_b (image right = right wing),
           y_c = -x_b (image up = nose).  A camera file's ``mount_rpy_deg`` rotates that nominal mounting by any
           rotation: a small misalignment, or an oblique or turned camera (CLIF's looks 9 deg right of the body's
           z axis with image x forward).  The camera model is OpenCV's pinhole (radial-tangential) or fisheye.
    ``s``  stabilised image (the *virtual nadir camera* of one TM cycle): a level pinhole camera at the
           aircraft, looking straight down, its image "up" (decreasing row) pointing along the cycle's base
           heading ``base_yaw_rad`` and its image right (increasing column) pointing 90 deg clockwise of it.
           Over flat ground this image is an orthographic map with a uniform ground sample distance
           ``gsd_m_px = height_agl_m / focal_px``.  Its window lies around the nadir (``stab.roi_centre =
           "nadir"``) or around the ground point of the raw image's centre (``"view"``, a camera that does not see
           the nadir); either way the steps below are the nadir's migration.
Displacements
    The template's migration is reported as ``dx_px`` (cross track, positive to the right of the base heading)
    and ``dy_px`` (along track, positive forward along the base heading), accumulated since the base snapshot.
    The paper's eq. 7-8 (``dX = X0 - LX``, ``dY = LY - Y0``) describe a camera image whose rows grow forward
    and whose columns grow to the left; in our ``s`` frame (rows grow backward, columns grow right) the same
    quantities are ``dx_px = LX - X0`` and ``dy_px = Y0 - LY``.  Drift (eq. 9) is then ``atan2(dx, dy)``:
    positive when the ground track lies clockwise (to the right) of the heading.
Names
    ``vec_a`` is a vector expressed in frame ``a``; ``R_ab`` rotates a vector from frame ``b`` to frame ``a``
    (``vec_a = R_ab @ vec_b``).  Units are SI and angles radians inside the code; degrees only at the edges
    (config files, CLI, plots, MAVLink fields defined in degrees), and then the name says so (``hfov_deg``).
    Boundary values carry their unit in the name: ``t_us`` (integer microseconds, one clock),
    ``airspeed_m_s``, ``height_agl_m``, ``yaw_rad``, ``wind_ned_m_s``.
Angles
    Headings, courses and wind directions are clockwise from north; wind direction is the direction the wind
    blows *from* (as MAVLink WIND).  Angles that wrap are compared only through :mod:`common.angles`.
"""

__all__ = ["__version__"]
__version__ = "0.1.0"
