"""needletissue.imaging"""
