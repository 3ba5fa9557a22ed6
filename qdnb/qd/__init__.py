"""Quality-diversity: tessellations, repertoires, variation, novelty, metrics, MAP-Elites
over any scoring function (``map_elites``), the policy-search algorithms of the book
(``algorithms``, ``pga``, ``qdpg``) and fast adaptation (``adaptation``)."""
