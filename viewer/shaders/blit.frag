// The window's blit: the renderer's final image scaled to the viewport (LINEAR sampler on unit 0).
uniform sampler2D image;
uniform vec2 viewport;  // viewport size in pixels
uniform vec2 origin;  // its lower-left corner in window pixels (the panel is left of it)
out vec4 color;
void main() { color = vec4(texture(image, (gl_FragCoord.xy - origin) / viewport).rgb, 1.0); }
