"""Quality-diversity: tessellations, repertoires, variation, metrics and loops."""
