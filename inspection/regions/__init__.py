"""Context-free region growing of paper 002 (`region_growing`), its multi-scale local surface
features (`local_features`) and the segmentation scores alpha, beta, eta (`segmetrics`)."""
