"""needletissue.geometry"""
