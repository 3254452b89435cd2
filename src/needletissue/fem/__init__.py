"""needletissue.fem"""
