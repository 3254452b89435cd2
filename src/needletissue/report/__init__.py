"""needletissue.report"""
