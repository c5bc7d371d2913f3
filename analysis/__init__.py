"""Analysis: FRFs, modal parameters, the 3D ODS, correlation and export."""
