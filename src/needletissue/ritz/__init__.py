"""needletissue.ritz"""
