"""Pure UFL of the dual formulation: the pre-dual Lagrangian and each scene's force, H and DtP map."""
