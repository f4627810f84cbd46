"""Distribution: the queries over dask arrays and frames over a Dask cluster
(dask; users import it as hlbvh_cl.dask).  It imports everything below
it, the Scene through its public API and borrow() seam."""
