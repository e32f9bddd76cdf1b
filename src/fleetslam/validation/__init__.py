"""What settings and endpoints may be, checked before anything uses them."""
