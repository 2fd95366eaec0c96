"""Sites: real districts, ray-traced once, as channel environments.

:mod:`sim.sites.format` (the ``tupa-site/1`` directory, its checks and hash),
:mod:`sim.sites.lookup` (path loss at any UAV position, numpy only), :mod:`sim.sites.los`
(line of sight; a call's losses and line of sight, `site_links`), :mod:`sim.sites.ground`
(walkable ground: where users may stand and walk),
:mod:`sim.sites.build` and :mod:`sim.sites.raytrace` (building one with Sionna RT, which only
``raytrace`` imports, inside its functions), :mod:`sim.sites.cli` (``tupa site build``).
``sim/sites/data/NAME/`` holds the sites shipped in the package (``munich``), which
``environment = site:NAME`` takes (:func:`sim.config.site_directory`); their map data's
attribution and licence are in ``sim/sites/data/README.md`` and each ``site.json``.
"""

from sim.sites.format import Site, load_site, save_site
from sim.sites.lookup import path_loss_db

__all__ = ["Site", "load_site", "path_loss_db", "save_site"]
