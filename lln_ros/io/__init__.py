"""Reading and writing: images, datasets, MCAP bags, the backbone feature cache, downloads."""
