// The window's blit: the renderer's final image scaled to the viewport (LINEAR sampler on unit 0).
uniform sampler2D image;
uniform vec2 viewport;  // viewport size in pixels (origin at 0, 0)
out vec4 color;
void main() { color = vec4(texture(image, gl_FragCoord.xy / viewport).rgb, 1.0); }
